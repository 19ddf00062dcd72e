//! A throwaway PostgreSQL cluster for the tests: Debian's `postgresql` binaries, `initdb` into a
//! temp dir, a server on a free loopback port, one fresh database per caller. No system service
//! and no root-owned state: as root (CI), the cluster runs as the `postgres` user, since initdb
//! refuses root.
//!
//! One cluster per test process, started on first use. A watchdog shell started with it stops
//! the server and removes its directory once the test process is gone, however it ends (a Rust
//! static is never dropped, and a panicking test must not leave a server behind).
//!
//! Without the binaries the tests that need them skip with a loud message, unless
//! `SAFEDICE_REQUIRE_POSTGRES=1` (set by `.ci/run`) makes that a failure.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use sqlx::Connection;

/// The running cluster. (`bin`, `data` and `options` serve stopping and starting a private
/// cluster, which only tests/fleet does: dead code in the other binaries.)
#[allow(dead_code)]
pub struct Cluster {
    port: u16,
    /// Where its binaries are, its data directory and its server options: what stopping and
    /// starting it again needs.
    bin: PathBuf,
    data: PathBuf,
    options: String,
}

static CLUSTER: OnceLock<Option<Cluster>> = OnceLock::new();

/// The test process's cluster, started on first call; None (after printing why) when
/// PostgreSQL is not installed and not required.
pub fn cluster() -> Option<&'static Cluster> {
    CLUSTER
        .get_or_init(|| if available() { bin_dir().map(|bin| Cluster::start(&bin)) } else { None })
        .as_ref()
}

/// Whether PostgreSQL's binaries are here. Without them: a panic where they are required, else
/// false after a loud message that the PostgreSQL tests are skipped.
pub fn available() -> bool {
    if bin_dir().is_some() {
        return true;
    }
    assert!(
        !required(),
        "SAFEDICE_REQUIRE_POSTGRES is set but PostgreSQL's binaries (initdb, pg_ctl) were not \
         found; install Debian's postgresql package or set SAFEDICE_PG_BIN"
    );
    eprintln!(
        "\n*** SKIPPING PostgreSQL tests: initdb/pg_ctl not found (install Debian's postgresql \
         package, or set SAFEDICE_PG_BIN) ***\n"
    );
    false
}

/// A cluster of the caller's own, for a test that stops and starts the server (the shared one
/// must stay up for the tests beside it); None as for [`cluster`].
#[allow(dead_code)]
pub fn private_cluster() -> Option<Cluster> {
    cluster()?;
    Some(Cluster::start(&bin_dir()?))
}

fn required() -> bool {
    std::env::var("SAFEDICE_REQUIRE_POSTGRES").is_ok_and(|v| v == "1")
}

/// Where initdb and pg_ctl are: $SAFEDICE_PG_BIN, the newest /usr/lib/postgresql/<v>/bin
/// (Debian does not put them on PATH), or PATH.
fn bin_dir() -> Option<PathBuf> {
    if let Some(dir) = std::env::var_os("SAFEDICE_PG_BIN") {
        return Some(PathBuf::from(dir));
    }
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|entry| {
            let version = entry.file_name().to_str()?.parse().ok()?;
            let bin = entry.path().join("bin");
            bin.join("initdb").exists().then_some((version, bin))
        })
        .collect();
    versions.sort();
    if let Some((_, bin)) = versions.pop() {
        return Some(bin);
    }
    let on_path = Command::new("sh").args(["-c", "command -v initdb"]).output().ok()?;
    let initdb = String::from_utf8(on_path.stdout).ok()?;
    Path::new(initdb.trim()).parent().map(Path::to_path_buf)
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|out| String::from_utf8_lossy(&out.stdout).trim() == "0")
}

/// A shell command run as the cluster's owner: `postgres` when we are root.
fn as_owner(script: &str) -> Command {
    let mut command = if is_root() {
        let mut c = Command::new("runuser");
        c.args(["-u", "postgres", "--", "sh", "-c", script]);
        c
    } else {
        let mut c = Command::new("sh");
        c.args(["-c", script]);
        c
    };
    command.stdin(Stdio::null());
    command
}

impl Cluster {
    fn start(bin: &Path) -> Cluster {
        let dir = tempfile::Builder::new().prefix("safedice-pg-").tempdir().unwrap().keep();
        if is_root() {
            let status = Command::new("chown").arg("postgres:").arg(&dir).status().unwrap();
            assert!(status.success(), "chown of the cluster directory to postgres failed");
        }
        let port = free_port();
        let (bin, data, pid) = (bin.display(), dir.join("data"), std::process::id());
        let data = data.display();
        let initdb = format!(
            "'{bin}/initdb' -D '{data}' -U postgres --auth=trust --encoding=UTF8 --no-sync \
             >'{data}.initdb.log' 2>&1"
        );
        let status = as_owner(&initdb).status().expect("run initdb");
        assert!(status.success(), "initdb failed; see {data}.initdb.log");
        // fsync off: a test cluster need not survive a power cut, and syncs dominate its time.
        let options = format!(
            "-p {port} -c listen_addresses=127.0.0.1 -k '{}' -c fsync=off -c \
             synchronous_commit=off -c full_page_writes=off -c max_connections=300",
            dir.display()
        );
        let watchdog = format!(
            "'{bin}/pg_ctl' -D '{data}' -o \"{options}\" -l '{data}.log' -w start >/dev/null && \
             while [ -d /proc/{pid} ]; do sleep 1; done; \
             '{bin}/pg_ctl' -D '{data}' -m immediate stop >/dev/null 2>&1; rm -rf '{}'",
            dir.display()
        );
        // Never waited for: it outlives this process on purpose, to clean up after it.
        #[allow(clippy::zombie_processes)]
        as_owner(&watchdog)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start the PostgreSQL watchdog");
        let cluster = Cluster {
            port,
            bin: PathBuf::from(bin.to_string()),
            data: PathBuf::from(data.to_string()),
            options,
        };
        cluster.wait_until_ready(&bin.to_string(), &format!("{data}.log"));
        cluster
    }

    #[allow(dead_code)]
    /// Stops the server (`pg_ctl stop -m fast`: clients are disconnected, nothing is lost) and
    /// waits until it is down. Its watchdog keeps waiting, so [`Self::start_again`] works.
    pub fn stop(&self) {
        let (bin, data) = (self.bin.display(), self.data.display());
        let stop = format!("'{bin}/pg_ctl' -D '{data}' -m fast -w stop >/dev/null");
        assert!(as_owner(&stop).status().expect("run pg_ctl stop").success(), "pg_ctl stop failed");
    }

    #[allow(dead_code)]
    /// Starts the stopped server again on the same port and data; returns once it is ready.
    pub fn start_again(&self) {
        let (bin, data) = (self.bin.display(), self.data.display());
        let start = format!(
            "'{bin}/pg_ctl' -D '{data}' -o \"{}\" -l '{data}.log' -w start >/dev/null",
            self.options
        );
        assert!(
            as_owner(&start).status().expect("run pg_ctl start").success(),
            "pg_ctl start failed"
        );
        self.wait_until_ready(&bin.to_string(), &format!("{data}.log"));
    }

    fn admin_url(&self) -> String {
        format!("postgres://postgres@127.0.0.1:{}/postgres", self.port)
    }

    /// Blocks until the server accepts queries (pg_isready; callers may be inside a runtime).
    fn wait_until_ready(&self, bin: &str, log: &str) {
        let started = Instant::now();
        let port = self.port.to_string();
        let ready = || {
            Command::new(format!("{bin}/pg_isready"))
                .args(["-q", "-h", "127.0.0.1", "-p", &port, "-U", "postgres"])
                .status()
                .is_ok_and(|status| status.success())
        };
        while !ready() {
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "PostgreSQL did not start; see {log}"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// A new, empty database of its own: its URL.
    pub async fn new_database(&self) -> String {
        let name = format!("t_{}", uuid::Uuid::new_v4().simple());
        let mut admin = sqlx::PgConnection::connect(&self.admin_url()).await.unwrap();
        sqlx::query(&format!("CREATE DATABASE {name}")).execute(&mut admin).await.unwrap();
        admin.close().await.unwrap();
        format!("postgres://postgres@127.0.0.1:{}/{name}", self.port)
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}
