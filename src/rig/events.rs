//! The session's event log, `SESSION/events.jsonl`: every pause, retry, recovery step and
//! unreadable controller line of a capture, one JSON object per line.
//!
//! # Format
//! ```text
//! {"time":"2026-11-23T07:12:03Z","kind":"pause","detail":"pair 001-stage-X-40.000: alarm: …"}
//! ```
//! - `time`: UTC, seconds precision (as `session.toml`).
//! - `kind`: `session-start`, `session-end`, `pause`, `retry`, `recovered`, `gave-up`,
//!   `reconnect`, `reset`, `rehome`, `unlock`, and the controller's own kinds
//!   (`corrupt-line`, `resync`, `response-assumed`, `stray-response`; see
//!   [`ControllerEvent`](super::controller::ControllerEvent)).
//! - `detail`: free text for a person; a `pause` names the cause first (`alarm:`,
//!   `disconnect:`, `camera-timeout:`, `drift:`, `controller-timeout:`, `unreadable:`,
//!   `protocol:`).
//!
//! The file is only appended to (a resumed session continues it), and every line is
//! written with one `write` and synced before the capture goes on, so a kill or a power cut
//! loses at most the line being written; a torn last line is skipped by [`read_events`].
//! (An append-only log cannot be written by rename like the other session files.)

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// One line of `events.jsonl`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Event {
    pub time: String,
    pub kind: String,
    pub detail: String,
}

/// Why the event log could not be written or read; names the file.
#[derive(Debug, thiserror::Error)]
#[error("{path}: cannot write the event log")]
pub struct EventLogError {
    pub path: PathBuf,
    #[source]
    pub source: std::io::Error,
}

/// An open `events.jsonl`, appended to.
#[derive(Debug)]
pub struct EventLog {
    path: PathBuf,
    file: File,
}

impl EventLog {
    /// The log's file name inside a session directory.
    pub const FILE: &'static str = "events.jsonl";

    /// Opens (creating) `dir/events.jsonl` for appending.
    ///
    /// # Errors
    /// The file cannot be created or opened.
    pub fn open(dir: &Path) -> Result<Self, EventLogError> {
        let path = dir.join(Self::FILE);
        let file = OpenOptions::new().create(true).append(true).open(&path).map_err(|source| EventLogError { path: path.clone(), source })?;
        Ok(Self { path, file })
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends one event and syncs it to disk.
    ///
    /// # Errors
    /// The write or the sync failed (a full disk).
    pub fn record(&mut self, kind: &str, detail: &str) -> Result<(), EventLogError> {
        let e = Event { time: crate::timestamp_utc(), kind: kind.into(), detail: detail.into() };
        // serde_json escapes control characters, so a garbled line stays on one line
        let mut line = serde_json::to_string(&e).map_err(|e| EventLogError { path: self.path.clone(), source: std::io::Error::other(e) })?;
        line.push('\n');
        let r = self.file.write_all(line.as_bytes()).and_then(|()| self.file.sync_data());
        r.map_err(|source| EventLogError { path: self.path.clone(), source })
    }
}

/// Reads every complete event of a log (a torn last line, from a kill mid-write, is skipped).
///
/// # Errors
/// The file cannot be read.
pub fn read_events(path: &Path) -> Result<Vec<Event>, EventLogError> {
    let text = std::fs::read_to_string(path).map_err(|source| EventLogError { path: path.to_path_buf(), source })?;
    Ok(text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_append_one_object_per_line_and_survive_a_torn_tail() {
        let dir = tempfile::tempdir().unwrap();
        let mut log = EventLog::open(dir.path()).unwrap();
        log.record("pause", "pair 000: alarm: ALARM:1").unwrap();
        log.record("corrupt-line", "\"<Run|MPos:-54.056,0.000,-8.000|FS:50,,0|\\r\u{fffd}\"").unwrap();
        drop(log);
        // reopening appends
        EventLog::open(dir.path()).unwrap().record("retry", "try 2 of 3").unwrap();
        let path = dir.path().join(EventLog::FILE);
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.lines().count(), 3, "{text}");
        for l in text.lines() {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            assert_eq!(v.as_object().unwrap().len(), 3, "{l}");
            assert!(v["time"].as_str().unwrap().ends_with('Z'));
        }
        std::fs::write(&path, format!("{text}{{\"time\":\"2026")).unwrap();
        let ev = read_events(&path).unwrap();
        assert_eq!(ev.iter().map(|e| e.kind.as_str()).collect::<Vec<_>>(), ["pause", "corrupt-line", "retry"]);
        assert!(ev[1].detail.contains("FS:50,,0"));
    }
}
