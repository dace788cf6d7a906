//! The page's side of the link, pure: the messages a page sends (JSON over its WebSocket), and
//! who may open that link.
//!
//! The lab listens on loopback only (its link is plain `ws://`), and even there a web page of another
//! site, open in the operator's browser, could open a WebSocket to it (WebSockets are not held
//! to the same-origin rule). So the link needs the lab's access token (generated at each start
//! unless one is configured; the page carries it in its URL's fragment, which no server or
//! log sees), its `Origin` must be the lab's own, and its `Host` must be
//! a loopback name (a DNS-rebinding page names its own host).

use crate::teleop::Command;
use body::ik::ToolTarget;
use serde::Deserialize;
use std::collections::BTreeMap;
use thiserror::Error;

/// What a page sends. (Variants without fields are written `{}` so that serde refuses unknown
/// fields in them too.)
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum PageMessage {
    /// Joint targets by name, rad.
    Joints {
        /// Name → rad.
        goals: BTreeMap<String, f64>,
    },
    /// An arm's tool to a pose in the base's frame.
    Tool {
        /// The arm's bus name (`left_arm`).
        arm: String,
        /// m.
        position: [f64; 3],
        /// `[w, x, y, z]`.
        rotation: [f64; 4],
    },
    /// The controlling page is still there.
    Alive {},
    /// The page lets go of the arms.
    Release {},
    /// Stop the robot (the supervisor's stop: its safe state until resumed).
    Stop {},
    /// End the stop.
    Resume {},
    /// Start recording an episode of `task`.
    RecordStart {
        /// What is demonstrated.
        task: String,
    },
    /// End the episode and keep it.
    RecordStop {},
    /// End the episode and throw it away.
    RecordDiscard {},
}

impl PageMessage {
    /// The teleoperation command this is, if it is one.
    pub fn command(&self) -> Option<Command> {
        Some(match self {
            PageMessage::Joints { goals } => Command::Joints(goals.clone()),
            PageMessage::Tool {
                arm,
                position,
                rotation,
            } => Command::Tool {
                arm: arm.clone(),
                target: ToolTarget {
                    position: *position,
                    rotation: *rotation,
                },
            },
            PageMessage::Alive {} => Command::Alive,
            PageMessage::Release {} => Command::Release,
            PageMessage::Stop {}
            | PageMessage::Resume {}
            | PageMessage::RecordStart { .. }
            | PageMessage::RecordStop {}
            | PageMessage::RecordDiscard {} => return None,
        })
    }
}

/// A message that is not one.
#[derive(Debug, Error, PartialEq)]
#[error("malformed page message: {0}")]
pub struct Malformed(pub String);

/// Largest message a page sends, bytes (a joints message naming every joint fits many times).
pub const MAX_MESSAGE: usize = 8 * 1024;

/// Parses a page's message.
pub fn parse(text: &str) -> Result<PageMessage, Malformed> {
    if text.len() > MAX_MESSAGE {
        return Err(Malformed(format!(
            "{} bytes (at most {MAX_MESSAGE})",
            text.len()
        )));
    }
    serde_json::from_str(text).map_err(|e| Malformed(e.to_string()))
}

/// Why a link was refused.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum Denied {
    /// No token, or not the lab's.
    #[error("no valid access token")]
    Token,
    /// `Host` is missing, or not a loopback name.
    #[error("host {0:?} is not this lab's")]
    Host(String),
    /// `Origin` is not the lab's own.
    #[error("origin {0:?} is not this lab's")]
    Origin(String),
}

/// Who may open the page's link.
#[derive(Debug, Clone)]
pub struct Access {
    token: String,
}

impl Access {
    /// `token` opens the link (the lab listens on a loopback address only).
    pub fn new(token: String) -> Access {
        Access { token }
    }

    /// Checks a request for the link: its `Host` and `Origin` headers and the token it
    /// carries.
    pub fn check(
        &self,
        host: Option<&str>,
        origin: Option<&str>,
        token: Option<&str>,
    ) -> Result<(), Denied> {
        let host = host.ok_or_else(|| Denied::Host(String::new()))?;
        if !is_loopback_host(host) {
            return Err(Denied::Host(host.to_string()));
        }
        if let Some(origin) = origin {
            let own = ["http://", "https://"]
                .iter()
                .any(|scheme| origin.strip_prefix(scheme) == Some(host));
            if !own {
                return Err(Denied::Origin(origin.to_string()));
            }
        }
        match token {
            Some(t) if same(t.as_bytes(), self.token.as_bytes()) => Ok(()),
            _ => Err(Denied::Token),
        }
    }
}

/// `host[:port]` names this machine's loopback.
fn is_loopback_host(host: &str) -> bool {
    let name = if let Some(v6) = host.strip_prefix('[') {
        v6.split(']').next().unwrap_or("")
    } else {
        host.rsplit_once(':').map_or(host, |(n, _)| n)
    };
    name == "localhost"
        || name
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// Compares in time that depends on the lengths only.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The value of `key` in a URL's query (`/ws?token=...`), undecoded (tokens are hex).
pub fn query_value<'a>(path: &'a str, key: &str) -> Option<&'a str> {
    let (_, query) = path.split_once('?')?;
    query
        .split('&')
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| *k == key)
        .map(|(_, v)| v)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn messages_parse_and_bad_ones_are_refused_with_the_reason() {
        assert_eq!(
            parse(r#"{"type":"joints","goals":{"left_elbow":-1.0}}"#).unwrap(),
            PageMessage::Joints {
                goals: [("left_elbow".to_string(), -1.0)].into()
            }
        );
        let tool = parse(
            r#"{"type":"tool","arm":"left_arm","position":[0.3,0.2,0.9],"rotation":[1,0,0,0]}"#,
        )
        .unwrap();
        assert!(matches!(tool.command(), Some(Command::Tool { ref arm, .. }) if arm == "left_arm"));
        assert_eq!(parse(r#"{"type":"stop"}"#).unwrap().command(), None);
        for (bad, why) in [
            (r#"{"type":"joints","goals":{"a":"x"}}"#, "invalid type"),
            (
                r#"{"type":"joints","goals":{"a":1e999}}"#,
                "number out of range",
            ),
            (
                r#"{"type":"tool","arm":"l","position":[1,2],"rotation":[1,0,0,0]}"#,
                "invalid length",
            ),
            (r#"{"type":"launch"}"#, "unknown variant"),
            (r#"{"type":"alive","extra":1}"#, "unknown field"),
            ("not json", "expected"),
        ] {
            let e = parse(bad).unwrap_err().to_string();
            assert!(e.contains(why), "{bad}: {e}");
        }
        let huge = format!(r#"{{"type":"alive","pad":"{}"}}"#, "x".repeat(MAX_MESSAGE));
        assert!(parse(&huge).unwrap_err().to_string().contains("at most"));
        // Up to 8 KiB is read (a joints message naming every joint with long names).
        let pad = |n: usize| format!(r#"{{"type":"joints","goals":{{"{}":0.5}}}}"#, "j".repeat(n));
        let at_most = pad(MAX_MESSAGE - pad(0).len());
        assert_eq!(at_most.len(), MAX_MESSAGE);
        assert!(matches!(parse(&at_most), Ok(PageMessage::Joints { .. })));
        assert!(parse(&pad(MAX_MESSAGE - pad(0).len() + 1)).is_err());
    }

    #[test]
    fn only_this_labs_pages_with_its_token_get_the_link() {
        let local = Access::new("abc123".into());
        let ok = |h, o, t| local.check(Some(h), o, Some(t));
        assert_eq!(
            ok("127.0.0.1:8765", Some("http://127.0.0.1:8765"), "abc123"),
            Ok(())
        );
        assert_eq!(ok("localhost:8765", None, "abc123"), Ok(()));
        assert_eq!(
            ok("[::1]:8765", Some("http://[::1]:8765"), "abc123"),
            Ok(())
        );
        assert_eq!(ok("127.0.0.1:8765", None, "abc124"), Err(Denied::Token));
        assert_eq!(ok("127.0.0.1:8765", None, "abc12"), Err(Denied::Token));
        // Two differences that would cancel if they were combined by exclusive or.
        assert_eq!(ok("127.0.0.1:8765", None, "bac123"), Err(Denied::Token));
        assert_eq!(
            local.check(Some("127.0.0.1:8765"), None, None),
            Err(Denied::Token)
        );
        // Another site's page, and a rebinding name for loopback.
        assert_eq!(
            ok("127.0.0.1:8765", Some("http://evil.example"), "abc123"),
            Err(Denied::Origin("http://evil.example".into()))
        );
        assert_eq!(
            ok(
                "evil.example:8765",
                Some("http://evil.example:8765"),
                "abc123"
            ),
            Err(Denied::Host("evil.example:8765".into()))
        );
        assert!(local.check(None, None, Some("abc123")).is_err());
        assert_eq!(query_value("/ws?a=1&token=ff00", "token"), Some("ff00"));
        assert_eq!(query_value("/ws", "token"), None);
    }
}
