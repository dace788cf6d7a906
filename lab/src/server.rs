//! The lab's HTTP and WebSocket server on std's TCP: the page's files, and one WebSocket per
//! open page (a thread each). Nothing here waits on the lab's loop or the loop on it: what a
//! page sends goes into a channel the loop drains, and what the loop sends a page goes into
//! that page's short queue, dropped (and counted) when the page does not keep up, so a stalled
//! browser never holds the robot's goals. A page that cannot take a message within a second is
//! closed (its teleoperation ends at once).

use crate::page::{self, Access, Malformed, PageMessage};
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, Sender, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tungstenite::protocol::{Role, WebSocketConfig};
use tungstenite::{Message, WebSocket};

/// What a page did, for the lab's loop.
#[derive(Debug)]
pub enum Event {
    /// A page opened its link.
    Opened,
    /// It sent a message (or something that is not one).
    Message(Result<PageMessage, Malformed>),
    /// Its link closed.
    Closed,
}

/// A page's event, with the page and when it arrived (CLOCK_MONOTONIC ns).
#[derive(Debug)]
pub struct Inbound {
    /// The page (numbered from 1 in the order they connect).
    pub page: u64,
    /// What happened.
    pub event: Event,
    /// When it arrived, CLOCK_MONOTONIC ns.
    pub at_ns: u64,
}

/// What the lab sends a page: JSON text, or a camera's JPEG (binary: a byte `1`, the camera
/// name's length, the name, the JPEG as the camera sent it).
#[derive(Debug, Clone)]
pub enum Outgoing {
    /// A JSON message.
    Text(Arc<str>),
    /// A binary message.
    Binary(Arc<[u8]>),
}

/// Messages queued per page before the newest are dropped.
const OUTBOX: usize = 8;
/// How long a page's thread waits for the page before it looks at its queue again.
const POLL: Duration = Duration::from_millis(2);
/// A page that takes no bytes for this long is closed.
const WRITE_TIMEOUT: Duration = Duration::from_secs(1);
/// Largest HTTP request head, bytes.
const MAX_HEAD: usize = 16 * 1024;

/// The open pages' queues, and what was dropped or refused.
#[derive(Default)]
pub struct Pages {
    outboxes: Mutex<Vec<(u64, SyncSender<Outgoing>)>>,
    next_page: AtomicU64,
    /// Messages dropped because a page did not keep up.
    pub dropped: AtomicU64,
    /// Link requests refused (token, host, origin).
    pub denied: AtomicU64,
}

impl Pages {
    /// Queues `text` for every open page.
    pub fn broadcast(&self, text: &Arc<str>) {
        self.broadcast_message(&Outgoing::Text(text.clone()));
    }

    /// Queues `message` for every open page.
    pub fn broadcast_message(&self, message: &Outgoing) {
        let outboxes = self.outboxes.lock().unwrap_or_else(PoisonError::into_inner);
        for (_, tx) in outboxes.iter() {
            self.queue(tx, message.clone());
        }
    }

    /// Queues `text` for page `page`.
    pub fn send(&self, page: u64, text: Arc<str>) {
        let outboxes = self.outboxes.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some((_, tx)) = outboxes.iter().find(|(p, _)| *p == page) {
            self.queue(tx, Outgoing::Text(text));
        }
    }

    /// Pages open now.
    pub fn open(&self) -> usize {
        self.outboxes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .len()
    }

    fn queue(&self, tx: &SyncSender<Outgoing>, message: Outgoing) {
        if let Err(TrySendError::Full(_)) = tx.try_send(message) {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn add(&self) -> (u64, Receiver<Outgoing>) {
        let page = self.next_page.fetch_add(1, Ordering::Relaxed) + 1;
        let (tx, rx) = mpsc::sync_channel(OUTBOX);
        self.outboxes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push((page, tx));
        (page, rx)
    }

    fn remove(&self, page: u64) {
        self.outboxes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .retain(|(p, _)| *p != page);
    }
}

/// The page's files.
#[derive(Debug, Clone, Copy)]
pub struct Files {
    /// `/`.
    pub index_html: &'static str,
    /// `/lab.js`.
    pub lab_js: &'static str,
}

/// Serves `listener` until `shutdown`: the files, and each page's link for the loop
/// (`inbound`), the pages' queues in `pages`.
pub fn serve(
    listener: TcpListener,
    files: Files,
    access: Access,
    pages: Arc<Pages>,
    inbound: Sender<Inbound>,
    shutdown: Arc<AtomicBool>,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    listener.set_nonblocking(true)?;
    std::thread::Builder::new()
        .name("lab-http".into())
        .spawn(move || {
            while !shutdown.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((stream, _)) => {
                        let (access, pages, inbound, shutdown) = (
                            access.clone(),
                            pages.clone(),
                            inbound.clone(),
                            shutdown.clone(),
                        );
                        let spawned =
                            std::thread::Builder::new()
                                .name("lab-page".into())
                                .spawn(move || {
                                    if let Err(e) = connection(
                                        stream, files, &access, &pages, &inbound, &shutdown,
                                    ) {
                                        tracing::debug!("connection: {e}");
                                    }
                                });
                        if let Err(e) = spawned {
                            tracing::warn!("no thread for a connection: {e}");
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        std::thread::sleep(Duration::from_millis(10));
                    }
                    Err(e) => {
                        tracing::warn!("accept: {e}");
                        std::thread::sleep(Duration::from_millis(100));
                    }
                }
            }
        })
}

/// One request's head.
struct Head {
    method: String,
    path: String,
    host: Option<String>,
    origin: Option<String>,
    upgrade: bool,
    key: Option<String>,
}

fn read_head(stream: &mut TcpStream) -> std::io::Result<Option<Head>> {
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 1024];
    loop {
        let n = stream.read(&mut chunk)?;
        if n == 0 {
            return Ok(None);
        }
        buf.extend_from_slice(&chunk[..n]);
        let mut headers = [httparse::EMPTY_HEADER; 48];
        let mut req = httparse::Request::new(&mut headers);
        match req.parse(&buf) {
            Ok(httparse::Status::Complete(_)) => {
                let header = |name: &str| {
                    req.headers
                        .iter()
                        .find(|h| h.name.eq_ignore_ascii_case(name))
                        .and_then(|h| std::str::from_utf8(h.value).ok())
                        .map(str::to_string)
                };
                return Ok(Some(Head {
                    method: req.method.unwrap_or("").to_string(),
                    path: req.path.unwrap_or("").to_string(),
                    upgrade: header("upgrade").is_some_and(|u| u.eq_ignore_ascii_case("websocket")),
                    key: header("sec-websocket-key"),
                    host: header("host"),
                    origin: header("origin"),
                }));
            }
            Ok(httparse::Status::Partial) if buf.len() < MAX_HEAD => continue,
            _ => return Ok(None),
        }
    }
}

fn respond(stream: &mut TcpStream, status: &str, kind: &str, body: &str) -> std::io::Result<()> {
    write!(
        stream,
        "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\nCache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )?;
    stream.flush()
}

fn connection(
    mut stream: TcpStream,
    files: Files,
    access: &Access,
    pages: &Pages,
    inbound: &Sender<Inbound>,
    shutdown: &AtomicBool,
) -> std::io::Result<()> {
    stream.set_nonblocking(false)?;
    let Some(head) = read_head(&mut stream)? else {
        return Ok(());
    };
    let route = head.path.split('?').next().unwrap_or("");
    if head.method != "GET" {
        return respond(
            &mut stream,
            "405 Method Not Allowed",
            "text/plain",
            "GET only\n",
        );
    }
    match (route, head.upgrade) {
        ("/", false) | ("/index.html", false) => respond(
            &mut stream,
            "200 OK",
            "text/html; charset=utf-8",
            files.index_html,
        ),
        ("/lab.js", false) => respond(
            &mut stream,
            "200 OK",
            "text/javascript; charset=utf-8",
            files.lab_js,
        ),
        ("/ws", true) => {
            let token = page::query_value(&head.path, "token");
            if let Err(denied) = access.check(head.host.as_deref(), head.origin.as_deref(), token) {
                pages.denied.fetch_add(1, Ordering::Relaxed);
                tracing::warn!("page link refused: {denied}");
                return respond(
                    &mut stream,
                    "403 Forbidden",
                    "text/plain",
                    &format!("{denied}\n"),
                );
            }
            let Some(key) = head.key else {
                return respond(
                    &mut stream,
                    "400 Bad Request",
                    "text/plain",
                    "no Sec-WebSocket-Key\n",
                );
            };
            let accept = tungstenite::handshake::derive_accept_key(key.as_bytes());
            write!(
                stream,
                "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Accept: {accept}\r\n\r\n"
            )?;
            stream.flush()?;
            link(stream, pages, inbound, shutdown)
        }
        _ => respond(&mut stream, "404 Not Found", "text/plain", "not found\n"),
    }
}

/// A page's WebSocket until it closes, fails, falls a second behind, or the lab stops.
fn link(
    stream: TcpStream,
    pages: &Pages,
    inbound: &Sender<Inbound>,
    shutdown: &AtomicBool,
) -> std::io::Result<()> {
    stream.set_read_timeout(Some(POLL))?;
    stream.set_write_timeout(Some(WRITE_TIMEOUT))?;
    stream.set_nodelay(true)?;
    let config = WebSocketConfig::default()
        .max_message_size(Some(page::MAX_MESSAGE * 2))
        .max_frame_size(Some(page::MAX_MESSAGE * 2));
    let mut ws = WebSocket::from_raw_socket(stream, Role::Server, Some(config));
    let (id, outbox) = pages.add();
    let now = telemetry::clock::monotonic_ns;
    let tell = |event| {
        let _ = inbound.send(Inbound {
            page: id,
            event,
            at_ns: now(),
        });
    };
    tell(Event::Opened);
    let result = (|| -> Result<(), tungstenite::Error> {
        while !shutdown.load(Ordering::Relaxed) {
            match ws.read() {
                Ok(Message::Text(text)) => tell(Event::Message(page::parse(text.as_str()))),
                Ok(Message::Binary(_)) => tell(Event::Message(Err(Malformed(
                    "a binary message (the page sends JSON text)".into(),
                )))),
                Ok(Message::Close(_)) => return Ok(()),
                Ok(_) => {}
                Err(tungstenite::Error::Io(e))
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(e) => return Err(e),
            }
            while let Ok(message) = outbox.try_recv() {
                ws.send(match message {
                    Outgoing::Text(text) => Message::text(text.as_ref()),
                    Outgoing::Binary(bytes) => Message::binary(bytes.to_vec()),
                })?;
            }
        }
        let _ = ws.close(None);
        let _ = ws.flush();
        Ok(())
    })();
    pages.remove(id);
    tell(Event::Closed);
    match result {
        Ok(()) | Err(tungstenite::Error::ConnectionClosed) => Ok(()),
        Err(e) => Err(std::io::Error::other(e)),
    }
}
