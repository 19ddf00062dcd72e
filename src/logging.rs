//! Process-wide logging. Logging must never take the service down or stall it: log lines go
//! through a bounded in-memory queue to a dedicated writer thread (a full queue drops lines,
//! never blocks a request), and a sink that fails (a closed pipe when `| head` exits or a log
//! shipper restarts, a full disk) loses lines instead of raising an error that would panic in
//! whichever task logged.

use std::io::{self, IsTerminal, Write};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use tracing_appender::non_blocking::{NonBlockingBuilder, WorkerGuard};

use crate::config::LogFormat;

/// Lines the writer thread holds before new ones are dropped.
const QUEUED_LINES: usize = 16_384;

/// Keeps the writer thread alive; dropping it flushes what is queued (at most about a second).
#[must_use = "logging stops when the guard is dropped"]
pub struct LogGuard {
    _worker: WorkerGuard,
}

/// Installs the global `tracing` subscriber writing to stdout; `RUST_LOG` overrides the
/// default filter. Colours only when stdout is a terminal (never ANSI codes in files or pipes).
pub fn init(format: LogFormat) -> LogGuard {
    let (writer, worker) = NonBlockingBuilder::default()
        .lossy(true)
        .buffered_lines_limit(QUEUED_LINES)
        .thread_name("safedice-log")
        .finish(LossySink::new(io::stdout()));
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(writer)
        .with_ansi(io::stdout().is_terminal())
        // The default reports a failed write with `eprintln!`, which panics when stderr is a
        // closed pipe too.
        .log_internal_errors(false);
    match format {
        LogFormat::Json => builder.json().with_current_span(true).init(),
        LogFormat::Pretty => builder.init(),
    }
    LogGuard { _worker: worker }
}

/// A writer that reports success whatever its inner writer does, counting the bytes it lost.
pub struct LossySink<W> {
    inner: W,
    broken: bool,
    lost_bytes: Arc<AtomicU64>,
}

impl<W: Write> LossySink<W> {
    pub fn new(inner: W) -> Self {
        LossySink { inner, broken: false, lost_bytes: Arc::new(AtomicU64::new(0)) }
    }

    /// Bytes that could not be written so far.
    pub fn lost_bytes(&self) -> Arc<AtomicU64> {
        self.lost_bytes.clone()
    }
}

impl<W: Write> Write for LossySink<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        // A closed pipe stays closed: stop trying rather than fail on every line.
        if self.broken || self.inner.write_all(buf).is_err() {
            self.broken = true;
            self.lost_bytes.fetch_add(buf.len() as u64, Ordering::Relaxed);
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        if !self.broken && self.inner.flush().is_err() {
            self.broken = true;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A writer that fails like a pipe whose reader has gone.
    struct ClosedPipe;

    impl Write for ClosedPipe {
        fn write(&mut self, _: &[u8]) -> io::Result<usize> {
            Err(io::Error::from(io::ErrorKind::BrokenPipe))
        }
        fn flush(&mut self) -> io::Result<()> {
            Err(io::Error::from(io::ErrorKind::BrokenPipe))
        }
    }

    #[test]
    fn a_failing_sink_loses_lines_without_an_error() {
        let mut sink = LossySink::new(ClosedPipe);
        let lost = sink.lost_bytes();
        assert_eq!(sink.write(b"first line\n").unwrap(), 11);
        writeln!(sink, "second line").unwrap();
        sink.flush().unwrap();
        assert_eq!(lost.load(Ordering::Relaxed), 23);
    }

    #[test]
    fn a_working_sink_passes_everything_through() {
        let mut sink = LossySink::new(Vec::new());
        writeln!(sink, "a line").unwrap();
        assert_eq!(sink.inner, b"a line\n");
        assert_eq!(sink.lost_bytes().load(Ordering::Relaxed), 0);
    }
}
