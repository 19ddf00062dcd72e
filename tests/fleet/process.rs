//! The processes of a test fleet: one API node and its workers, each a child process of the
//! real binary with a data directory of its own and its log in a file.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::support::postgres;

/// Seconds of a lease in the test fleet: short, so a takeover comes quickly.
const LEASE_SECONDS: &str = "3";
const RETRY_BACKOFF_SECONDS: &str = "1";

/// A child process and where its log goes.
struct Process {
    child: Child,
    log: PathBuf,
}

impl Process {
    fn spawn(args: &[String], log: PathBuf) -> Process {
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
    /// The PostgreSQL database, or the SQLite file's URL when the processes share one SQLite
    /// data directory.
    pub database_url: String,
    /// Some: every process uses this SQLite data directory (no --database-url).
    shared_sqlite: Option<PathBuf>,
    pub api_url: String,
    pub client: reqwest::Client,
    dir: tempfile::TempDir,
    _api: Process,
    workers: Vec<Process>,
    /// More API nodes started by [`Fleet::start_api_node`].
    more_api: Vec<Process>,
    store_args: Vec<String>,
}

impl Fleet {
    /// Starts the API node and `workers` workers; None when PostgreSQL is not installed (the
    /// cluster support said so loudly).
    pub async fn start(workers: usize) -> Option<Fleet> {
        let database_url = postgres::cluster()?.new_database().await;
        Some(Fleet::start_on(Some(database_url), workers).await)
    }

    /// The same on a database of the caller's (e.g. on a private cluster it stops and starts).
    pub async fn start_on_database(database_url: String, workers: usize) -> Fleet {
        Fleet::start_on(Some(database_url), workers).await
    }

    /// The same on SQLite: every process on this machine shares one data directory.
    pub async fn start_sqlite(workers: usize) -> Fleet {
        Fleet::start_on(None, workers).await
    }

    async fn start_on(database_url: Option<String>, workers: usize) -> Fleet {
        let dir = tempfile::tempdir().unwrap();
        let shared_sqlite = database_url.is_none().then(|| dir.path().join("shared"));
        let store_args = |own: PathBuf| -> Vec<String> {
            let data_dir = shared_sqlite.clone().unwrap_or(own);
            let mut args = vec!["--data-dir".to_owned(), data_dir.display().to_string()];
            args.extend(
                database_url.iter().flat_map(|url| ["--database-url".to_owned(), url.clone()]),
            );
            args
        };
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let bind = format!("127.0.0.1:{port}");
        let mut api_args: Vec<String> =
            ["serve", "--workers", "0", "--bind", &bind].map(str::to_owned).to_vec();
        api_args.extend(store_args(dir.path().join("api")));
        let node_store_args = store_args(dir.path().join("api-2"));
        let api = Process::spawn(&api_args, dir.path().join("api.log"));
        let database_url = database_url.unwrap_or_else(|| {
            let file = shared_sqlite.as_ref().unwrap().join("safedice.sqlite");
            format!("sqlite://{}", file.display())
        });
        let mut fleet = Fleet {
            database_url,
            shared_sqlite,
            api_url: format!("http://{bind}"),
            client: reqwest::Client::new(),
            dir,
            _api: api,
            workers: Vec::new(),
            more_api: Vec::new(),
            store_args: node_store_args,
        };
        fleet.wait_for_api().await;
        for _ in 0..workers {
            fleet.start_worker();
        }
        fleet
    }

    async fn wait_for_api(&self) {
        let started = Instant::now();
        let ready = format!("{}/readyz", self.api_url);
        while !self.client.get(&ready).send().await.is_ok_and(|r| r.status().is_success()) {
            assert!(started.elapsed() < Duration::from_secs(60), "the API node did not come up");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Starts a second API node (`serve --workers 0`) on the same store; its URL once ready.
    pub async fn start_api_node(&mut self) -> String {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let url = format!("http://127.0.0.1:{port}");
        let bind = format!("127.0.0.1:{port}");
        let mut args: Vec<String> =
            ["serve", "--workers", "0", "--bind", &bind].map(str::to_owned).to_vec();
        args.extend(self.store_args.iter().cloned());
        let log = self.dir.path().join(format!("api-{}.log", self.more_api.len() + 2));
        self.more_api.push(Process::spawn(&args, log));
        let started = Instant::now();
        while !self
            .client
            .get(format!("{url}/readyz"))
            .send()
            .await
            .is_ok_and(|r| r.status().is_success())
        {
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "the second API node did not come up"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        url
    }

    /// Starts one more worker process (its own data directory).
    pub fn start_worker(&mut self) {
        let index = self.workers.len();
        let own = self.dir.path().join(format!("worker-{index}"));
        let mut args = vec!["worker".to_owned(), "--lease-seconds".into(), LEASE_SECONDS.into()];
        // A short retry backoff: takeovers stay prompt, and a retry still waits a little.
        args.extend(["--retry-backoff-secs".to_owned(), RETRY_BACKOFF_SECONDS.into()]);
        args.push("--data-dir".into());
        args.push(self.shared_sqlite.clone().unwrap_or(own).display().to_string());
        if self.shared_sqlite.is_none() {
            args.extend(["--database-url".to_owned(), self.database_url.clone()]);
        }
        let worker = Process::spawn(&args, self.dir.path().join(format!("worker-{index}.log")));
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
