//! Crash recovery: the server runs as a child process (the real `safedice serve` binary), is
//! killed with SIGKILL mid-training, and restarted on the same data directory. The job must
//! resume from its last checkpoint (not from step 0), finish, store every recorded metric row
//! exactly once with the values an uninterrupted run records, and produce bitwise the policy an
//! uninterrupted run with the same seed produces.

mod jobs_support;

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::str::FromStr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use jobs_support::*;
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
            .args(["serve", "--bind", &format!("127.0.0.1:{port}"), "--data-dir"])
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

/// The uninterrupted run in-process: its recorded metrics (same `log_every` rule as the
/// runner) and its policy weights.
fn uninterrupted_run(config: &ResolvedConfig, log_every: u64) -> (Metrics, Vec<u8>) {
    let (unlabeled, non_preferred) = grid_datasets();
    let data = TrainingData {
        unlabeled: Arc::new(unlabeled),
        non_preferred: Some(Arc::new(non_preferred)),
    };
    let mut trainer = algo::build_trainer(config, &data, None).unwrap();
    let mut metrics = Metrics::new();
    let total = config.total_steps();
    while !trainer.is_finished() {
        let next = trainer.progress().step + 1;
        let record = next % log_every == 0 || next == total;
        for (name, value) in trainer.step(record).unwrap() {
            metrics.insert((name.to_owned(), next as i64), value);
        }
    }
    (metrics, trainer.export_policy().unwrap().weights)
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
    let job = create_job(
        &client,
        &server.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": small_config(3000, 5),
               "runner": {"log_every": log_every, "checkpoint_every": checkpoint_every}}),
    )
    .await;
    let id = job["id"].as_str().unwrap().to_owned();
    let total = job["progress"]["total"].as_u64().unwrap();
    // Kill once a few checkpoints exist but well before the end.
    wait_for_job(&client, &server.base_url, &id, Duration::from_secs(300), |j| {
        j["progress"]["step"].as_u64().unwrap() >= 3 * checkpoint_every
    })
    .await;
    server.kill();

    let mut conn = db(data_dir.path()).await;
    let (status,): (String,) = sqlx::query_as("SELECT status FROM jobs WHERE id = ?")
        .bind(&id)
        .fetch_one(&mut conn)
        .await
        .unwrap();
    let (checkpoint_step,): (i64,) =
        sqlx::query_as("SELECT step FROM job_checkpoints WHERE job_id = ?")
            .bind(&id)
            .fetch_one(&mut conn)
            .await
            .unwrap();
    conn.close().await.unwrap();
    assert_eq!(status, "running", "killed mid-training");
    assert!(checkpoint_step >= 3 * checkpoint_every as i64 - checkpoint_every as i64);
    assert!((checkpoint_step as u64) < total, "the job had not finished");

    let server = ServerProcess::start(data_dir.path()).await;
    // A resume from step 0 would report step 0 for half a second; polling would see it.
    let lowest = std::cell::Cell::new(u64::MAX);
    let finished = wait_for_job(&client, &server.base_url, &id, Duration::from_secs(300), |j| {
        if j["status"] == "running" {
            lowest.set(lowest.get().min(j["progress"]["step"].as_u64().unwrap()));
        }
        j["status"] == "succeeded"
    })
    .await;
    assert!(
        lowest.get() >= checkpoint_step as u64,
        "resumed at step {}, not the checkpoint",
        lowest.get()
    );
    assert_eq!(finished["progress"]["step"].as_u64(), Some(total));

    let config: ResolvedConfig = serde_json::from_value(finished["config"].clone()).unwrap();
    let (expected_metrics, expected_weights) = uninterrupted_run(&config, log_every);
    let mut conn = db(data_dir.path()).await;
    let rows: Vec<(String, i64, f64)> = sqlx::query_as(
        "SELECT name, step, value FROM job_metrics WHERE job_id = ? ORDER BY name, step",
    )
    .bind(&id)
    .fetch_all(&mut conn)
    .await
    .unwrap();
    conn.close().await.unwrap();
    let stored: Metrics = rows.iter().map(|(n, s, v)| ((n.clone(), *s), *v)).collect();
    assert_eq!(stored.len(), rows.len(), "no (name, step) row twice");
    assert_eq!(stored, expected_metrics, "every recorded row once, with the uninterrupted values");

    let policy_id = finished["policy_id"].as_str().unwrap();
    let weights = client
        .get(format!("{}/v1/policies/{policy_id}/weights", server.base_url))
        .send()
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    assert!(weights[..] == expected_weights[..], "the resumed policy equals the uninterrupted one");
}
