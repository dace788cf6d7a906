//! Headless Chromium driven over its DevTools protocol (a WebSocket): Nori Lab's page in a real
//! browser, for the process tests and the benchmarks. Debian's `chromium`
//! (`deploy/install-build-deps.sh` installs it).

use crate::child::{ChildError, Managed};
use serde_json::{json, Value};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use thiserror::Error;
use tungstenite::stream::MaybeTlsStream;
use tungstenite::{Message, WebSocket};

/// What went wrong with the browser.
#[derive(Debug, Error)]
pub enum BrowserError {
    /// It could not be started.
    #[error("starting chromium: {0}")]
    Start(#[from] ChildError),
    /// It showed no page to drive within 30 s.
    #[error("chromium showed no page target on {0} within 30 s")]
    NoPage(String),
    /// The DevTools link failed.
    #[error("the DevTools link: {0}")]
    Link(#[from] tungstenite::Error),
    /// A call was answered with an error (or a script threw).
    #[error("{method}: {error}")]
    Call {
        /// The DevTools method.
        method: String,
        /// Its answer.
        error: String,
    },
    /// An answer that is not JSON, or a screenshot that is not base64.
    #[error("a DevTools answer that cannot be read: {0}")]
    Answer(String),
}

/// Debian's Chromium on the `PATH`, if installed.
pub fn chromium() -> Option<PathBuf> {
    let paths = std::env::var_os("PATH")?;
    ["chromium", "chromium-browser"].iter().find_map(|name| {
        std::env::split_paths(&paths)
            .map(|d| d.join(name))
            .find(|p| p.exists())
    })
}

/// One page of a headless Chromium of its own (profile under `dir`), driven over DevTools.
pub struct Browser {
    process: Managed,
    devtools: WebSocket<MaybeTlsStream<TcpStream>>,
    next_id: u64,
}

/// A GET in HTTP/1.1 (Chromium's DevTools server answers no 1.0, and keeps the connection
/// open: the body is read by its length): the body of a 200.
fn get(address: &str, path: &str) -> Option<String> {
    use std::io::{Read, Write};
    let mut stream = TcpStream::connect(address).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut raw = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        let n = stream.read(&mut chunk).ok()?;
        if n == 0 {
            return None;
        }
        raw.extend_from_slice(&chunk[..n]);
        let Some(end) = raw.windows(4).position(|w| w == b"\r\n\r\n") else {
            continue;
        };
        let head = String::from_utf8_lossy(&raw[..end]).to_ascii_lowercase();
        let length: usize = head
            .lines()
            .find_map(|l| l.strip_prefix("content-length:"))?
            .trim()
            .parse()
            .ok()?;
        if raw.len() >= end + 4 + length {
            let body = String::from_utf8_lossy(&raw[end + 4..end + 4 + length]).into_owned();
            return head.starts_with("http/1.1 200").then_some(body);
        }
    }
}

impl Browser {
    /// Starts `chromium` headless at `url` (a 1300 × 900 window, device scale 1) and connects
    /// to its page.
    pub fn open(chromium: &Path, url: &str, dir: &Path) -> Result<Browser, BrowserError> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .map_err(|e| {
                BrowserError::Start(ChildError::Spawn {
                    name: "chromium".into(),
                    source: e,
                })
            })?;
        let args: Vec<String> = [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--force-device-scale-factor=1",
            "--window-size=1300,900",
        ]
        .iter()
        .map(|s| s.to_string())
        .chain([
            format!("--remote-debugging-port={port}"),
            format!("--user-data-dir={}", dir.join("chromium-profile").display()),
            url.to_string(),
        ])
        .collect();
        let mut process = Managed::new("chromium", chromium, &args);
        process.log_to(&dir.join("chromium.log"))?;
        process.start()?;
        let address = format!("127.0.0.1:{port}");
        let until = Instant::now() + Duration::from_secs(30);
        let page = loop {
            let target = get(&address, "/json/list")
                .and_then(|text| serde_json::from_str::<Value>(&text).ok())
                .and_then(|list| {
                    list.as_array()?
                        .iter()
                        .find(|t| t["type"] == "page")
                        .and_then(|t| t["webSocketDebuggerUrl"].as_str())
                        .map(str::to_string)
                });
            if let Some(t) = target {
                break t;
            }
            if Instant::now() > until {
                return Err(BrowserError::NoPage(address));
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        let (devtools, _) = tungstenite::connect(page.as_str())?;
        if let MaybeTlsStream::Plain(s) = devtools.get_ref() {
            s.set_read_timeout(Some(Duration::from_secs(20)))
                .map_err(|e| BrowserError::Link(e.into()))?;
        }
        Ok(Browser {
            process,
            devtools,
            next_id: 0,
        })
    }

    /// The browser's process id (its process group's).
    pub fn pid(&self) -> Option<u32> {
        self.process.pid()
    }

    /// Sends a DevTools call without waiting; its id for [`Browser::answer`].
    pub fn send(&mut self, method: &str, params: Value) -> Result<u64, BrowserError> {
        self.next_id += 1;
        let msg = json!({"id": self.next_id, "method": method, "params": params});
        self.devtools.send(Message::text(msg.to_string()))?;
        Ok(self.next_id)
    }

    /// The answer to call `id` (events in between are passed over).
    pub fn answer(&mut self, id: u64, method: &str) -> Result<Value, BrowserError> {
        loop {
            let Message::Text(text) = self.devtools.read()? else {
                continue;
            };
            let v: Value = serde_json::from_str(text.as_str())
                .map_err(|e| BrowserError::Answer(e.to_string()))?;
            if v["id"] == id {
                if let Some(e) = v.get("error") {
                    return Err(BrowserError::Call {
                        method: method.into(),
                        error: e.to_string(),
                    });
                }
                return Ok(v["result"].clone());
            }
        }
    }

    /// A DevTools call's result.
    pub fn call(&mut self, method: &str, params: Value) -> Result<Value, BrowserError> {
        let id = self.send(method, params)?;
        self.answer(id, method)
    }

    /// The value of a script in the page (awaited if it is a promise).
    pub fn eval(&mut self, script: &str) -> Result<Value, BrowserError> {
        let r = self.call(
            "Runtime.evaluate",
            json!({"expression": script, "returnByValue": true, "awaitPromise": true}),
        )?;
        if let Some(e) = r.get("exceptionDetails") {
            return Err(BrowserError::Call {
                method: format!("evaluating {script:?}"),
                error: e.to_string(),
            });
        }
        Ok(r["result"]["value"].clone())
    }

    /// A mouse event (`mousePressed`, `mouseMoved`, `mouseReleased`) with the left button, at
    /// CSS pixels `x`, `y`.
    pub fn mouse(&mut self, kind: &str, x: f64, y: f64) -> Result<(), BrowserError> {
        let buttons = if kind == "mouseReleased" { 0 } else { 1 };
        self.call(
            "Input.dispatchMouseEvent",
            json!({"type": kind, "x": x, "y": y, "button": "left", "buttons": buttons, "clickCount": 1}),
        )
        .map(drop)
    }

    /// Clicks the middle of the element `selector`.
    pub fn click(&mut self, selector: &str) -> Result<(), BrowserError> {
        let r = self.eval(&format!(
            "(() => {{ const r = document.querySelector('{selector}').getBoundingClientRect(); return [r.left + r.width / 2, r.top + r.height / 2]; }})()"
        ))?;
        let (x, y) = (r[0].as_f64().unwrap_or(0.0), r[1].as_f64().unwrap_or(0.0));
        self.mouse("mousePressed", x, y)?;
        self.mouse("mouseReleased", x, y)
    }

    /// A key press and release (`ArrowUp`, ...), without waiting for either to be handled; the
    /// ids of the two calls.
    pub fn send_key(&mut self, key: &str) -> Result<[u64; 2], BrowserError> {
        let down = self.send(
            "Input.dispatchKeyEvent",
            json!({"type": "rawKeyDown", "key": key, "code": key, "windowsVirtualKeyCode": virtual_key(key)}),
        )?;
        let up = self.send(
            "Input.dispatchKeyEvent",
            json!({"type": "keyUp", "key": key, "code": key, "windowsVirtualKeyCode": virtual_key(key)}),
        )?;
        Ok([down, up])
    }

    /// The page as it is on screen, PNG.
    pub fn screenshot_png(&mut self) -> Result<Vec<u8>, BrowserError> {
        use base64::Engine;
        let r = self.call("Page.captureScreenshot", json!({"format": "png"}))?;
        base64::engine::general_purpose::STANDARD
            .decode(r["data"].as_str().unwrap_or(""))
            .map_err(|e| BrowserError::Answer(e.to_string()))
    }
}

/// Windows virtual key codes Chromium wants with a key event.
fn virtual_key(key: &str) -> u32 {
    match key {
        "ArrowLeft" => 37,
        "ArrowUp" => 38,
        "ArrowRight" => 39,
        "ArrowDown" => 40,
        "PageUp" => 33,
        "PageDown" => 34,
        _ => 0,
    }
}
