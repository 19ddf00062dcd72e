//! The processes of a test fleet: one API node and its workers, each a child process of the
//! real binary with a data directory of its own and its log in a file.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::support::postgres;

/// Seconds of a lease in the test fleet: short, so a takeover comes quickly.
const LEASE_SECONDS: &str = "3";

/// A child process and where its log goes.
struct Process {
    child: Child,
    log: PathBuf,
}

impl Process {
    fn spawn(args: &[&str], log: PathBuf) -> Process {
        let out = std::fs::File::create(&log).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_safedice"))
            .args(args)
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(out.try_clone().unwrap())
            .stderr(out)
            .spawn()
            .expect("start safedice");
        Process { child, log }
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        // A stopped process must be continued to die of SIGKILL promptly.
        let _ = Command::new("kill").args(["-CONT", &self.child.id().to_string()]).status();
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An API node (`serve --workers 0`) and `safedice worker` processes on one fresh database.
pub struct Fleet {
    pub database_url: String,
    pub api_url: String,
    pub client: reqwest::Client,
    dir: tempfile::TempDir,
    _api: Process,
    workers: Vec<Process>,
}

impl Fleet {
    /// Starts the API node and `workers` workers; None when PostgreSQL is not installed (the
    /// cluster support said so loudly).
    pub async fn start(workers: usize) -> Option<Fleet> {
        let database_url = postgres::cluster()?.new_database().await;
        let dir = tempfile::tempdir().unwrap();
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let bind = format!("127.0.0.1:{port}");
        let api_dir = dir.path().join("api");
        let api = Process::spawn(
            &[
                "serve",
                "--workers",
                "0",
                "--bind",
                &bind,
                "--database-url",
                &database_url,
                "--data-dir",
                api_dir.to_str().unwrap(),
            ],
            dir.path().join("api.log"),
        );
        let mut fleet = Fleet {
            database_url,
            api_url: format!("http://{bind}"),
            client: reqwest::Client::new(),
            dir,
            _api: api,
            workers: Vec::new(),
        };
        fleet.wait_for_api().await;
        for _ in 0..workers {
            fleet.start_worker();
        }
        Some(fleet)
    }

    async fn wait_for_api(&self) {
        let started = Instant::now();
        let ready = format!("{}/readyz", self.api_url);
        while !self.client.get(&ready).send().await.is_ok_and(|r| r.status().is_success()) {
            assert!(started.elapsed() < Duration::from_secs(60), "the API node did not come up");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Starts one more worker process (its own data directory).
    pub fn start_worker(&mut self) {
        let index = self.workers.len();
        let data_dir = self.dir.path().join(format!("worker-{index}"));
        let worker = Process::spawn(
            &[
                "worker",
                "--database-url",
                &self.database_url,
                "--data-dir",
                data_dir.to_str().unwrap(),
                "--lease-seconds",
                LEASE_SECONDS,
            ],
            self.dir.path().join(format!("worker-{index}.log")),
        );
        self.workers.push(worker);
    }

    /// The worker process whose id (`<host>-<pid>-<suffix>`) is `worker_id`.
    fn worker(&self, worker_id: &str) -> &Process {
        let pid = worker_id.rsplit('-').nth(1).expect("a worker id names its pid");
        self.workers
            .iter()
            .find(|w| w.child.id().to_string() == pid)
            .unwrap_or_else(|| panic!("no worker process {worker_id}"))
    }

    /// SIGKILL: no shutdown, no last write.
    pub fn kill_worker(&mut self, worker_id: &str) {
        self.signal_worker(worker_id, "KILL");
    }

    /// Sends `signal` (KILL, STOP, CONT) to the worker.
    pub fn signal_worker(&self, worker_id: &str, signal: &str) {
        let pid = self.worker(worker_id).child.id().to_string();
        let status = Command::new("kill").args([&format!("-{signal}"), &pid]).status().unwrap();
        assert!(status.success(), "kill -{signal} {pid}");
    }

    /// Waits until the worker's log has a line containing `text`.
    pub async fn wait_for_log(&self, worker_id: &str, text: &str, timeout: Duration) {
        let started = Instant::now();
        let worker = self.worker(worker_id);
        while !worker.log_text().contains(text) {
            assert!(
                started.elapsed() < timeout,
                "worker {worker_id} never logged {text:?}; its log:\n{}",
                worker.log_text()
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
}
