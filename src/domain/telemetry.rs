//! What a running job reports and who runs it: its metric samples, its log lines, and the
//! workers of the fleet. Typed records (times as times, counts unsigned); the store turns its
//! rows into these once, so `http/` and `jobs/` never see a stored string time.

use std::time::Duration;

use chrono::{DateTime, Utc};

/// One recorded scalar of a training step.
#[derive(Clone, Debug, PartialEq)]
pub struct MetricRecord {
    pub name: String,
    pub step: u64,
    pub value: f64,
    /// When the worker recorded it.
    pub time: DateTime<Utc>,
}

/// How bad a log line is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LogLevel {
    Info,
    Warn,
    Error,
}

impl LogLevel {
    pub const ALL: [LogLevel; 3] = [LogLevel::Info, LogLevel::Warn, LogLevel::Error];

    /// The word the store keeps and the API shows.
    pub fn as_str(self) -> &'static str {
        match self {
            LogLevel::Info => "info",
            LogLevel::Warn => "warn",
            LogLevel::Error => "error",
        }
    }

    /// The level [`LogLevel::as_str`] wrote, or `None` for any other word.
    pub fn parse(word: &str) -> Option<LogLevel> {
        LogLevel::ALL.into_iter().find(|level| level.as_str() == word)
    }
}

/// A line of a job's log.
#[derive(Clone, Debug, PartialEq)]
pub struct LogRecord {
    /// Its number in the job's log, from 1.
    pub seq: u64,
    pub time: DateTime<Utc>,
    pub level: LogLevel,
    /// The worker that wrote it.
    pub worker: String,
    pub message: String,
}

/// A worker in the fleet's registry.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkerRecord {
    pub id: String,
    pub host: String,
    pub pid: u32,
    /// Jobs it runs at once.
    pub concurrency: u32,
    pub started_at: DateTime<Utc>,
    /// Time since its last heartbeat, on the database's clock.
    pub heartbeat_age: Duration,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_levels_round_trip_through_their_words() {
        for level in LogLevel::ALL {
            assert_eq!(LogLevel::parse(level.as_str()), Some(level));
        }
        assert_eq!(LogLevel::parse("debug"), None);
        assert_eq!(LogLevel::parse("INFO"), None);
    }
}
