//! The job workers' own log (their `tracing` lines), kept in memory, for the tests that check
//! what a worker of an in-process test server reported about a job: what it logs goes nowhere
//! else (only `safedice serve` installs a subscriber, writing to stdout).
//!
//! One subscriber per test process, installed on first use and kept: every later test server of
//! the process logs into it too. Only the workers' lines are kept, and a test reads the lines of
//! its own job (the worker's span names the job id), so tests running beside it do not disturb
//! it.

use std::io::Write;
use std::sync::{Arc, Mutex, OnceLock};

use tracing_subscriber::fmt::MakeWriter;

/// The captured lines, from the installation on.
#[derive(Clone, Default)]
pub struct ServerLog {
    text: Arc<Mutex<Vec<u8>>>,
}

static LOG: OnceLock<ServerLog> = OnceLock::new();

/// Starts keeping the workers' log lines (before the server of the test starts, so none of its
/// lines is missed); the process's log from then on.
pub fn capture() -> ServerLog {
    LOG.get_or_init(|| {
        let log = ServerLog::default();
        let subscriber = tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::new("safedice::jobs::worker=info"))
            .with_ansi(false)
            .with_writer(log.clone())
            .finish();
        tracing::subscriber::set_global_default(subscriber)
            .expect("no other test installs a tracing subscriber");
        log
    })
    .clone()
}

impl ServerLog {
    /// The lines logged inside the worker's span for job `id` (its claims, its end).
    pub fn lines_of_job(&self, id: &str) -> Vec<String> {
        let text = self.text.lock().unwrap();
        String::from_utf8_lossy(&text)
            .lines()
            .filter(|line| line.contains(&format!("job_id={id}")))
            .map(str::to_owned)
            .collect()
    }
}

impl Write for ServerLog {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.text.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl<'a> MakeWriter<'a> for ServerLog {
    type Writer = ServerLog;

    fn make_writer(&'a self) -> ServerLog {
        self.clone()
    }
}
