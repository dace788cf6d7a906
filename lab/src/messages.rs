//! What the lab sends a page, typed (pure). Each message is a struct or an enum serialized by
//! serde with the `type` tag the page dispatches on (`page/lab.js`, `onmessage`), so a field
//! renamed here is renamed for the page, and the page's words for a decision (why teleoperation
//! ended, what a reply answers, why a command was refused) are the enums' own names. The model
//! and the state frames themselves are [`crate::scene`]'s; what a frame carries beside the arm
//! is [`FrameExtras`].

use crate::recording::{Outcome, RecordingStatus};
use crate::stop_button::{Answer, Press};
use crate::teleop::{Ended, Refusal, Solved, TeleopCounters};
use serde::Serialize;
use std::sync::Arc;
use telemetry::frames::SupervisorEvent;
use telemetry::motion::{lift_state_name, BaseState, LiftState};

/// A message to a page.
#[derive(Debug, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ToPage<'a> {
    /// The first message on a link: the page's number, its dead-man bound and the cameras.
    Hello {
        /// The page's number.
        page: u64,
        /// A controlling page silent this long is released, ms.
        deadman_ms: u64,
        /// The cameras whose images follow.
        cameras: &'a [String],
    },
    /// The answer to one of the page's messages.
    Reply(Reply),
    /// Teleoperation ended by itself.
    Ended {
        /// What ended it.
        why: Ended,
    },
    /// An episode recorded from a page ended.
    Recorded {
        /// How it ended: committed (with its index and frames), discarded, or the recorder failed.
        outcome: &'a Outcome,
    },
}

impl ToPage<'_> {
    /// The message as the text a page's link carries.
    pub fn text(&self) -> Result<Arc<str>, serde_json::Error> {
        serde_json::to_string(self).map(Into::into)
    }
}

/// What a reply answers, when not a teleoperation command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Subject {
    /// The stop button.
    Stop,
    /// The resume button.
    Resume,
    /// A record button.
    Record,
}

impl From<Press> for Subject {
    fn from(press: Press) -> Subject {
        match press {
            Press::Stop => Subject::Stop,
            Press::Resume => Subject::Resume,
        }
    }
}

/// A reply: whether the page's message was taken, and what the page shows for it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Reply {
    /// What it answers (absent: a teleoperation command, or a message not understood).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub to: Option<Subject>,
    /// Whether the message was taken (when not, `error` says why).
    pub ok: bool,
    /// What the page shows when taken.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub text: Option<&'static str>,
    /// Why not taken.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The refusal's kind ([`Refusal::kind`]), for the page to act on.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub refused: Option<&'static str>,
    /// A tool command's solution.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub solved: Option<Solved>,
}

impl Reply {
    fn refusal(to: Option<Subject>, error: String) -> Reply {
        Reply {
            to,
            ok: false,
            text: None,
            error: Some(error),
            refused: None,
            solved: None,
        }
    }

    /// A message that is not one the page sends.
    pub fn malformed(error: &impl std::fmt::Display) -> Reply {
        Reply::refusal(None, error.to_string())
    }

    /// A stop or resume press, answered.
    pub fn press(press: Press, answer: Answer) -> Reply {
        let (ok, text) = answer.reply(press);
        Reply {
            text: Some(text),
            ..Reply::refusal(Some(press.into()), text.to_string())
        }
        .taken_if(ok)
    }

    /// A press that could not be sent to the supervisor.
    pub fn unsent(press: Press, error: &impl std::fmt::Display) -> Reply {
        Reply::refusal(Some(press.into()), error.to_string())
    }

    /// A record button's outcome.
    pub fn record(done: Result<(), String>) -> Reply {
        match done {
            Ok(()) => Reply::refusal(Some(Subject::Record), String::new()).taken_if(true),
            Err(why) => Reply::refusal(Some(Subject::Record), why),
        }
    }

    /// A teleoperation command's outcome.
    pub fn teleop(outcome: Result<Option<Solved>, Refusal>) -> Reply {
        match outcome {
            Ok(solved) => Reply {
                solved,
                ..Reply::refusal(None, String::new()).taken_if(true)
            },
            Err(r) => Reply {
                refused: Some(r.kind()),
                ..Reply::refusal(None, r.to_string())
            },
        }
    }

    /// Taken (no error then) or not.
    fn taken_if(mut self, ok: bool) -> Reply {
        self.ok = ok;
        if ok {
            self.error = None;
        }
        self
    }
}

/// What a state frame carries beside the arms: teleoperation, the supervisor's recent
/// events, the pages, the recording, the cameras, the lift and the base.
#[derive(Debug, Serialize)]
pub struct FrameExtras<'a> {
    /// Who controls, what is commanded, what was counted.
    pub teleop: TeleopView<'a>,
    /// The supervisor's latest events, oldest first.
    pub events: &'a [EventView],
    /// Pages open.
    pub pages: usize,
    /// The page's recording (none without `--dataset`).
    pub recording: Option<RecordingStatus>,
    /// The cameras shown.
    pub cameras: Vec<CameraStatus>,
    /// The lift's newest state (none without a lift).
    pub lift: Option<LiftView>,
    /// The base's newest state (none without a base).
    pub base: Option<BaseView>,
}

/// Teleoperation, for the page.
#[derive(Debug, Serialize)]
pub struct TeleopView<'a> {
    /// The page in control.
    pub owner: Option<u64>,
    /// Joints commanded now (bit per frame index).
    pub active: u32,
    /// What it counted.
    #[serde(flatten)]
    pub counters: &'a TeleopCounters,
}

/// A supervisor event, for the page.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EventView {
    /// The event's kind (`unknown` for a kind this lab does not know).
    pub kind: String,
    /// Joint index.
    pub joint: u8,
    /// Bus index.
    pub bus: u8,
    /// Its level.
    pub level: u8,
    /// Its figure.
    pub value: f32,
}

impl From<&SupervisorEvent> for EventView {
    fn from(e: &SupervisorEvent) -> EventView {
        EventView {
            kind: e
                .kind()
                .map_or_else(|| "unknown".to_string(), |k| format!("{k:?}")),
            joint: e.joint,
            bus: e.bus,
            level: e.level,
            value: e.value,
        }
    }
}

/// A camera shown on the pages.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraStatus {
    /// Its name.
    pub name: String,
    /// Its newest image's width, pixels (0 before one).
    pub width: u32,
    /// Its newest image's height, pixels (0 before one).
    pub height: u32,
    /// Images sent to the pages.
    pub images: u64,
    /// Age of its newest image, ms.
    pub age_ms: Option<f64>,
}

/// The lift, for the page.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LiftView {
    /// Its state's name.
    pub state: &'static str,
    /// m, once homed.
    pub height_m: Option<f32>,
    /// m, while it has one.
    pub goal_m: Option<f32>,
    /// A.
    pub current_a: f32,
}

impl From<&LiftState> for LiftView {
    fn from(l: &LiftState) -> LiftView {
        LiftView {
            state: lift_state_name(l.state),
            height_m: l.height_m.is_finite().then_some(l.height_m),
            goal_m: l.goal_m.is_finite().then_some(l.goal_m),
            current_a: l.current_a,
        }
    }
}

/// The base, for the page.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BaseView {
    /// Odometry, m.
    pub x_m: f64,
    /// m.
    pub y_m: f64,
    /// rad.
    pub heading_rad: f64,
    /// Measured twist, m/s.
    pub linear_m_s: f32,
    /// rad/s.
    pub angular_rad_s: f32,
    /// Its flags' names.
    pub flags: Vec<&'static str>,
}

impl From<&BaseState> for BaseView {
    fn from(b: &BaseState) -> BaseView {
        BaseView {
            x_m: b.x_m,
            y_m: b.y_m,
            heading_rad: b.theta_rad,
            linear_m_s: b.linear_m_s,
            angular_rad_s: b.angular_rad_s,
            flags: b.flag_names().collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use serde_json::{json, Value};

    fn sent(m: &ToPage) -> Value {
        serde_json::from_str(&m.text().unwrap()).unwrap()
    }

    #[test]
    fn replies_carry_what_the_page_reads_and_nothing_it_would_misread() {
        let stop = Answer::Done;
        let (ok, text) = stop.reply(Press::Stop);
        assert!(ok);
        assert_eq!(
            sent(&ToPage::Reply(Reply::press(Press::Stop, stop))),
            json!({"type": "reply", "to": "stop", "ok": true, "text": text})
        );
        let nobody = Answer::Unheard;
        let (ok, text) = nobody.reply(Press::Resume);
        assert!(!ok);
        assert_eq!(
            sent(&ToPage::Reply(Reply::press(Press::Resume, nobody))),
            json!({"type": "reply", "to": "resume", "ok": false, "text": text, "error": text})
        );
        assert_eq!(
            sent(&ToPage::Reply(Reply::record(Err("busy".into())))),
            json!({"type": "reply", "to": "record", "ok": false, "error": "busy"})
        );
        assert_eq!(
            sent(&ToPage::Reply(Reply::record(Ok(())))),
            json!({"type": "reply", "to": "record", "ok": true})
        );
        let refused = Reply::teleop(Err(Refusal::Unreachable {
            position_error_m: 0.1,
            angle_error_rad: 0.2,
        }));
        let v = sent(&ToPage::Reply(refused));
        assert_eq!(v["ok"], false);
        assert_eq!(v["refused"], "unreachable");
        assert!(v["error"].as_str().unwrap().len() > 10, "{v}");
        let solved = Solved {
            position_error_m: 0.001,
            angle_error_rad: 0.002,
            starts: 2,
        };
        assert_eq!(
            sent(&ToPage::Reply(Reply::teleop(Ok(Some(solved))))),
            json!({"type": "reply", "ok": true, "solved":
                {"position_error_m": 0.001, "angle_error_rad": 0.002, "starts": 2}})
        );
    }

    #[test]
    fn a_recorded_episode_reads_as_the_page_and_its_tests_expect() {
        let saved = Outcome::Committed {
            episode: 3,
            frames: 91,
        };
        assert_eq!(
            sent(&ToPage::Recorded { outcome: &saved }),
            json!({"type": "recorded", "outcome": {"saved": true, "episode": 3, "frames": 91}})
        );
        assert_eq!(
            sent(&ToPage::Recorded {
                outcome: &Outcome::Discarded
            })["outcome"],
            json!({"discarded": true})
        );
        assert_eq!(
            sent(&ToPage::Recorded {
                outcome: &Outcome::Failed("disk full".into())
            })["outcome"],
            json!({"failed": "disk full"})
        );
    }

    #[test]
    fn every_way_teleoperation_ends_has_its_own_word_for_the_page() {
        let all = [
            Ended::DeadMan,
            Ended::PageClosed,
            Ended::Released,
            Ended::SafeState,
            Ended::DriverRestarted,
            Ended::DriverSilent,
        ];
        let words: Vec<Value> = all
            .iter()
            .map(|&why| sent(&ToPage::Ended { why })["why"].clone())
            .collect();
        assert_eq!(words[0], "dead_man");
        assert_eq!(words[1], "page_closed");
        let mut unique = words.clone();
        unique.dedup();
        assert_eq!(unique.len(), all.len(), "{words:?}");
    }

    #[test]
    fn a_lift_not_homed_shows_no_height_and_a_base_its_flags() {
        let lift = LiftState {
            height_m: f32::NAN,
            goal_m: 0.3,
            ..LiftState::default()
        };
        let v = serde_json::to_value(LiftView::from(&lift)).unwrap();
        assert_eq!(v["height_m"], Value::Null);
        assert!((v["goal_m"].as_f64().unwrap() - 0.3).abs() < 1e-6);
        let base = BaseState {
            theta_rad: 1.5,
            ..BaseState::default()
        };
        let v = serde_json::to_value(BaseView::from(&base)).unwrap();
        assert_eq!(v["heading_rad"], 1.5);
        assert!(v["flags"].is_array());
    }
}
