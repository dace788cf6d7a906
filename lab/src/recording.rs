//! Recording from the page through the same recorder as `nori record`: an episode is a
//! `nori record --episodes 1` of its own, started by the page's record button, ended by its
//! stop (SIGINT: the recorder commits the episode and says so on stdout) or thrown away by its
//! discard (SIGKILL, then `nori dataset recover --drop-unfinished`, which drops what the
//! killed recorder had staged). Every file and every crash-safety rule stays the recorder's;
//! the lab only counts what it reports. Nothing here blocks the lab's loop: each recorder is
//! waited for by a thread of its own.

use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use serde::ser::SerializeMap;
use serde::{Serialize, Serializer};
use serde_json::Value;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::mpsc::{self, Receiver, Sender};
use std::time::Instant;

/// What the lab records into, and with what.
#[derive(Debug, Clone)]
pub struct RecordingSettings {
    /// `nori` (next to `nori-lab`).
    pub nori: PathBuf,
    /// The dataset directory.
    pub dataset: PathBuf,
    /// The state-plane domain.
    pub domain: String,
    /// Cameras to record (`--camera`).
    pub cameras: Vec<String>,
    /// Where each recorder's log goes.
    pub log: PathBuf,
}

/// How an episode ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Committed: its index and frames.
    Committed {
        /// The episode's index in the dataset.
        episode: i64,
        /// Its frames.
        frames: u64,
    },
    /// Thrown away.
    Discarded,
    /// The recorder failed (its last log line says why).
    Failed(String),
}

enum Phase {
    Idle,
    Recording {
        pid: u32,
        task: String,
        since: Instant,
    },
    Ending {
        discard: bool,
    },
}

/// The page's recordings.
pub struct Recording {
    settings: RecordingSettings,
    phase: Phase,
    done_tx: Sender<Outcome>,
    done: Receiver<Outcome>,
    last: Option<Outcome>,
    /// Episodes in the dataset, as last read.
    episodes: u64,
}

impl Recording {
    /// Recording into `settings.dataset`.
    pub fn new(settings: RecordingSettings) -> Recording {
        let (done_tx, done) = mpsc::channel();
        let mut r = Recording {
            settings,
            phase: Phase::Idle,
            done_tx,
            done,
            last: None,
            episodes: 0,
        };
        r.episodes = r.count_episodes();
        r
    }

    /// Whether an episode is being recorded or saved.
    pub fn busy(&self) -> bool {
        !matches!(self.phase, Phase::Idle)
    }

    /// Episodes the dataset holds (its `meta/info.json`; 0 before the first).
    fn count_episodes(&self) -> u64 {
        std::fs::read_to_string(self.settings.dataset.join("meta/info.json"))
            .ok()
            .and_then(|t| serde_json::from_str::<Value>(&t).ok())
            .and_then(|v| v["total_episodes"].as_u64())
            .unwrap_or(0)
    }

    /// Starts an episode of `task`.
    pub fn start(&mut self, task: &str) -> Result<(), String> {
        if !matches!(self.phase, Phase::Idle) {
            return Err("an episode is being recorded or saved".into());
        }
        let task = task.trim();
        if task.is_empty() || task.len() > 500 {
            return Err("say what is demonstrated: a task text of 1 to 500 bytes".into());
        }
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.settings.log)
            .map_err(|e| format!("the recorder's log {}: {e}", self.settings.log.display()))?;
        let mut command = Command::new(&self.settings.nori);
        command
            .arg("record")
            .arg("--dataset")
            .arg(&self.settings.dataset)
            .args(["--task", task, "--episodes", "1", "--episode-s", "86400"])
            .args(["--domain", &self.settings.domain]);
        for c in &self.settings.cameras {
            command.args(["--camera", c]);
        }
        let child = command
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .map_err(|e| format!("starting {}: {e}", self.settings.nori.display()))?;
        let pid = child.id();
        let (tx, settings) = (self.done_tx.clone(), self.settings.clone());
        std::thread::Builder::new()
            .name("lab-recorder".into())
            .spawn(move || {
                let outcome = match child.wait_with_output() {
                    Ok(out) if out.status.success() => committed(&out.stdout),
                    Ok(out) if out.status.code().is_none() => {
                        // Killed: the discard. The recorder's own recovery drops what it staged.
                        let recovered = Command::new(&settings.nori)
                            .args(["dataset", "recover", "--drop-unfinished"])
                            .arg(&settings.dataset)
                            .stdout(Stdio::null())
                            .stderr(Stdio::null())
                            .status();
                        match recovered {
                            Ok(s) if s.success() => Outcome::Discarded,
                            other => Outcome::Failed(format!(
                                "the discarded episode's recovery failed: {other:?}"
                            )),
                        }
                    }
                    Ok(out) => Outcome::Failed(format!(
                        "the recorder exited with {} (its log: {})",
                        out.status,
                        settings.log.display()
                    )),
                    Err(e) => Outcome::Failed(format!("waiting for the recorder: {e}")),
                };
                let _ = tx.send(outcome);
            })
            .map_err(|e| format!("no thread for the recorder: {e}"))?;
        self.phase = Phase::Recording {
            pid,
            task: task.to_string(),
            since: Instant::now(),
        };
        Ok(())
    }

    /// Ends the episode and keeps it (`discard`: throws it away).
    pub fn end(&mut self, discard: bool) -> Result<(), String> {
        let Phase::Recording { pid, .. } = self.phase else {
            return Err("no episode is being recorded".into());
        };
        let signal = if discard {
            Signal::SIGKILL
        } else {
            Signal::SIGINT
        };
        kill(Pid::from_raw(pid as i32), signal)
            .map_err(|e| format!("signalling the recorder: {e}"))?;
        self.phase = Phase::Ending { discard };
        Ok(())
    }

    /// How the episode ended, once it has.
    pub fn poll(&mut self) -> Option<Outcome> {
        let outcome = self.done.try_recv().ok()?;
        self.phase = Phase::Idle;
        self.episodes = self.count_episodes();
        self.last = Some(outcome.clone());
        Some(outcome)
    }

    /// For the page.
    pub fn status(&self) -> RecordingStatus {
        let (state, task, seconds) = match &self.phase {
            Phase::Idle => (RecordingState::Idle, None, None),
            Phase::Recording { task, since, .. } => (
                RecordingState::Recording,
                Some(task.clone()),
                Some(since.elapsed().as_secs_f64()),
            ),
            Phase::Ending { discard: true } => (RecordingState::Discarding, None, None),
            Phase::Ending { discard: false } => (RecordingState::Saving, None, None),
        };
        RecordingStatus {
            state,
            task,
            seconds,
            episodes: self.episodes,
            dataset: self.settings.dataset.clone(),
            last: self.last.clone(),
        }
    }
}

/// What the page's recording is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RecordingState {
    /// Not recording: no episode under way.
    Idle,
    /// Recording an episode.
    Recording,
    /// Ending an episode to keep it.
    Saving,
    /// Ending an episode to throw it away.
    Discarding,
}

/// The page's recording, for the page.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RecordingStatus {
    /// What it does.
    pub state: RecordingState,
    /// The task being recorded.
    pub task: Option<String>,
    /// For how long, s.
    pub seconds: Option<f64>,
    /// Episodes in the dataset.
    pub episodes: u64,
    /// The dataset's directory.
    pub dataset: PathBuf,
    /// How the last episode ended.
    pub last: Option<Outcome>,
}

/// The episode `nori record` reports on stdout.
fn committed(stdout: &[u8]) -> Outcome {
    let v: Value = serde_json::from_slice(stdout).unwrap_or(Value::Null);
    match v["episodes"].as_array().and_then(|e| e.last()) {
        Some(e) => Outcome::Committed {
            episode: e["episode"].as_i64().unwrap_or(-1),
            frames: e["frames"].as_u64().unwrap_or(0),
        },
        None => Outcome::Failed("the recorder stopped before an episode began".into()),
    }
}

/// For the page: `{"saved": true, "episode", "frames"}`, `{"discarded": true}` or
/// `{"failed": why}`.
impl Serialize for Outcome {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut m = s.serialize_map(None)?;
        match self {
            Outcome::Committed { episode, frames } => {
                m.serialize_entry("saved", &true)?;
                m.serialize_entry("episode", episode)?;
                m.serialize_entry("frames", frames)?;
            }
            Outcome::Discarded => m.serialize_entry("discarded", &true)?,
            Outcome::Failed(why) => m.serialize_entry("failed", why)?,
        }
        m.end()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_recorders_report_names_the_committed_episode() {
        assert_eq!(
            committed(
                br#"{"dataset":"d","episodes":[{"episode":3,"frames":91}],"total_episodes":4}"#
            ),
            Outcome::Committed {
                episode: 3,
                frames: 91
            }
        );
        assert!(matches!(
            committed(br#"{"dataset":"d","episodes":[],"total_episodes":4}"#),
            Outcome::Failed(_)
        ));
        assert!(matches!(committed(b"garbage"), Outcome::Failed(_)));
    }
}
