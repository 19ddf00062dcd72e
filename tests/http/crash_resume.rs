//! Crash recovery: the server runs as a child process (the real `safedice serve` binary), is
//! killed with SIGKILL mid-training, and restarted on the same data directory. The job must
//! resume from its last checkpoint (not from step 0), store every recorded metric row exactly
//! once with the values an uninterrupted run records, and reach bitwise the state (weights,
//! optimiser moments, RNG) and the policy an uninterrupted run with the same seed reaches.
//!
//! The job is far longer than the test runs (`ENDLESS_ITERATIONS`), so each kill lands mid-run
//! whatever the speed of the build, with no production hook to hold the job there. It is
//! therefore never finished: the resumed run is killed again once it has saved checkpoints of
//! its own, and its last checkpoint is compared with an uninterrupted run stopped at that step.
//! A checkpoint holds the whole state of a run (src/algo/checkpoint.rs), so equal checkpoints
//! mean every later step is equal too.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::str::FromStr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::support::jobs::*;
use safedice::algo::{self, ResolvedConfig, TrainingData};
use serde_json::json;
use sqlx::sqlite::SqliteConnectOptions;
use sqlx::{Connection, SqliteConnection};

/// A `safedice serve` child process.
struct ServerProcess {
    child: Child,
    base_url: String,
}

impl ServerProcess {
    async fn start(data_dir: &Path) -> ServerProcess {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new(env!("CARGO_BIN_EXE_safedice"))
            // A short lease: the restarted server takes the killed one's job over once it
            // expires.
            .args(["serve", "--lease-seconds", "3", "--bind", &format!("127.0.0.1:{port}")])
            .arg("--data-dir")
            .arg(data_dir)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .expect("start safedice serve");
        let server = ServerProcess { child, base_url: format!("http://127.0.0.1:{port}") };
        let started = Instant::now();
        while reqwest::get(format!("{}/healthz", server.base_url)).await.is_err() {
            assert!(started.elapsed() < Duration::from_secs(60), "server did not come up");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        server
    }

    /// SIGKILL: no graceful shutdown, no final checkpoint.
    fn kill(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn db(data_dir: &Path) -> SqliteConnection {
    let options = SqliteConnectOptions::from_str("sqlite:")
        .unwrap()
        .filename(data_dir.join("safedice.sqlite"));
    SqliteConnection::connect_with(&options).await.unwrap()
}

type Metrics = BTreeMap<(String, i64), f64>;

/// A job's stored metric rows: (name, step) -> (value, time written).
type StoredRows = BTreeMap<(String, i64), (f64, String)>;

async fn stored_rows(conn: &mut SqliteConnection, job_id: &str) -> StoredRows {
    let rows: Vec<(String, i64, f64, String)> =
        sqlx::query_as("SELECT name, step, value, time FROM job_metrics WHERE job_id = ?")
            .bind(job_id)
            .fetch_all(conn)
            .await
            .unwrap();
    let count = rows.len();
    let stored: StoredRows = rows.into_iter().map(|(n, s, v, t)| ((n, s), (v, t))).collect();
    assert_eq!(stored.len(), count, "no (name, step) row twice");
    stored
}

/// A killed server's view of a job, read from its database.
struct KilledJob {
    status: String,
    /// The step the API shows: the last progress report, up to half a second off the checkpoint.
    shown_step: i64,
    checkpoint_step: i64,
    checkpoint: Vec<u8>,
    /// (name, step) -> (value, time written).
    rows: StoredRows,
}

async fn killed_job(data_dir: &Path, job_id: &str) -> KilledJob {
    let mut conn = db(data_dir).await;
    let (status, shown_step): (String, i64) =
        sqlx::query_as("SELECT status, step FROM jobs WHERE id = ?")
            .bind(job_id)
            .fetch_one(&mut conn)
            .await
            .unwrap();
    let (checkpoint_step, checkpoint): (i64, Vec<u8>) =
        sqlx::query_as("SELECT step, data FROM job_checkpoints WHERE job_id = ?")
            .bind(job_id)
            .fetch_one(&mut conn)
            .await
            .expect("the killed job has a checkpoint");
    let rows = stored_rows(&mut conn, job_id).await;
    conn.close().await.unwrap();
    KilledJob { status, shown_step, checkpoint_step, checkpoint, rows }
}

/// What the uninterrupted run in-process records up to step `last` (same `log_every` rule as
/// the runner), and its checkpoint and policy weights after step `at` (`at <= last`).
struct Uninterrupted {
    metrics: Metrics,
    checkpoint: Vec<u8>,
    weights: Vec<u8>,
}

fn grid_training_data() -> TrainingData {
    let (unlabeled, non_preferred) = grid_datasets();
    TrainingData { unlabeled: Arc::new(unlabeled), non_preferred: Some(Arc::new(non_preferred)) }
}

fn uninterrupted_run(config: &ResolvedConfig, log_every: u64, at: u64, last: u64) -> Uninterrupted {
    let mut trainer = algo::build_trainer(config, &grid_training_data(), None).unwrap();
    let mut metrics = Metrics::new();
    let total = config.total_steps();
    let mut state = None;
    while trainer.progress().step < last {
        let next = trainer.progress().step + 1;
        let record = next.is_multiple_of(log_every) || next == total;
        for (name, value) in trainer.step(record).unwrap() {
            metrics.insert((name.to_owned(), next as i64), value);
        }
        if next == at {
            state = Some((trainer.checkpoint().unwrap(), trainer.export_policy().unwrap().weights));
        }
    }
    let (checkpoint, weights) = state.expect("`at` is within the run");
    Uninterrupted { metrics, checkpoint, weights }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_server_resumes_the_job_from_its_checkpoint_with_identical_results() {
    let data_dir = tempfile::tempdir().unwrap();
    let client = reqwest::Client::new();
    let server = ServerProcess::start(data_dir.path()).await;
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&client, &server.base_url, &unlabeled, "u").await;
    let n = upload(&client, &server.base_url, &non_preferred, "n").await;
    let (log_every, checkpoint_every) = (10, 250);
    let mut config = small_config(ENDLESS_ITERATIONS, 5);
    // Short pretraining: the checkpoints compared below are in the policy phase.
    config["discriminator_iterations"] = json!(300);
    // On two threads: a resume must give the uninterrupted run's bits at the job's `threads`.
    config["threads"] = json!(2);
    let job = create_job(
        &client,
        &server.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": config,
               "runner": {"log_every": log_every, "checkpoint_every": checkpoint_every}}),
    )
    .await;
    let id = job["id"].as_str().unwrap().to_owned();
    let total = job["progress"]["total"].as_u64().unwrap() as i64;
    let checkpoint_every = checkpoint_every as i64;

    // First kill, once a few checkpoints exist (the job cannot have finished: it is endless).
    wait_for_job(&client, &server.base_url, &id, Duration::from_secs(300), |j| {
        j["progress"]["step"].as_i64().unwrap() >= 3 * checkpoint_every
    })
    .await;
    server.kill();
    let first = killed_job(data_dir.path(), &id).await;
    let checkpoint_step = first.checkpoint_step;
    assert_eq!(first.status, "running", "killed mid-training");
    assert!(checkpoint_step >= 3 * checkpoint_every && checkpoint_step % checkpoint_every == 0);
    assert!(checkpoint_step < total, "the job had not finished");
    let checkpointed_rows: StoredRows =
        first.rows.into_iter().filter(|((_, step), _)| *step <= checkpoint_step).collect();
    assert_eq!(checkpointed_rows.keys().map(|k| k.1).max(), Some(checkpoint_step));

    // Second kill, once the resumed run has saved two checkpoints of its own.
    let server = ServerProcess::start(data_dir.path()).await;
    let lowest = std::cell::Cell::new(i64::MAX);
    let resumed = wait_for_job(&client, &server.base_url, &id, Duration::from_secs(300), |j| {
        let step = j["progress"]["step"].as_i64().unwrap();
        if j["status"] == "running" {
            lowest.set(lowest.get().min(step));
        }
        j["status"] == "running" && step >= checkpoint_step + 2 * checkpoint_every
    })
    .await;
    server.kill();
    let second = killed_job(data_dir.path(), &id).await;
    let (last_checkpoint, stored) = (second.checkpoint_step, second.rows);
    assert_eq!(second.status, "running", "killed mid-training again");
    assert!(last_checkpoint >= checkpoint_step + 2 * checkpoint_every, "{last_checkpoint}");
    // The rows up to the first checkpoint are the ones written before the first kill, time
    // included: the resumed run did not recompute them, so it did not start before it.
    let kept: StoredRows =
        stored.clone().into_iter().filter(|((_, step), _)| *step <= checkpoint_step).collect();
    assert_eq!(kept, checkpointed_rows, "the rows up to the checkpoint were rewritten");
    // What polling saw agrees: a claimed job shows its last reported step until the resumed
    // run's first report (its checkpoint's step); a resume from 0 would likely show 0.
    let floor = first.shown_step.min(checkpoint_step);
    assert!(lowest.get() >= floor, "seen running at step {} < {floor}", lowest.get());

    // Rows are stored up to the last checkpoint at least (a checkpoint commits its rows), maybe
    // further (progress reports flush them too); all of them as the uninterrupted run has them.
    let config: ResolvedConfig = serde_json::from_value(resumed["config"].clone()).unwrap();
    let last_row = stored.keys().map(|k| k.1).max().unwrap();
    assert!(last_row >= last_checkpoint);
    let expected = uninterrupted_run(&config, log_every, last_checkpoint as u64, last_row as u64);
    let stored: Metrics = stored.into_iter().map(|(key, (value, _))| (key, value)).collect();
    assert_eq!(stored, expected.metrics, "every recorded row once, with the uninterrupted values");
    assert!(
        second.checkpoint == expected.checkpoint,
        "the resumed run's checkpoint at step {last_checkpoint} equals the uninterrupted one's"
    );
    let resumed_policy =
        algo::build_trainer(&config, &grid_training_data(), Some(&second.checkpoint))
            .unwrap()
            .export_policy()
            .unwrap()
            .weights;
    assert!(resumed_policy == expected.weights, "the resumed policy equals the uninterrupted one");
}
