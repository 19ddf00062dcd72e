//! A graceful restart (SIGTERM-like shutdown of the in-process server) mid-training: the
//! running job is checkpointed at shutdown and resumed from that checkpoint by the next server
//! on the same data, with every metric row stored once.

use std::time::Duration;

use crate::jobs::upload_grid;
use crate::support::app::{assert_error, TestApp};
use crate::support::jobs::*;
use reqwest::StatusCode;
use serde_json::json;

type MetricRows = std::collections::BTreeMap<(String, u64), (f64, String)>;

/// A stopped server's view of a job, read from its database.
struct StoppedJob {
    status: String,
    /// The step the API shows: the last progress report, up to half a second behind.
    shown_step: u64,
    /// The step of its checkpoint.
    checkpoint_step: u64,
    /// (name, step) -> (value, time written).
    rows: MetricRows,
}

async fn stopped_job(app: &TestApp, id: &str) -> StoppedJob {
    let mut db = app.db().await;
    let (status, shown_step): (String, i64) =
        sqlx::query_as("SELECT status, step FROM jobs WHERE id = $1")
            .bind(id)
            .fetch_one(&mut db)
            .await
            .unwrap();
    let checkpoint_step: i64 =
        sqlx::query_scalar("SELECT step FROM job_checkpoints WHERE job_id = $1")
            .bind(id)
            .fetch_one(&mut db)
            .await
            .expect("a stopped job keeps its shutdown checkpoint");
    let rows: Vec<(String, i64, f64, String)> =
        sqlx::query_as("SELECT name, step, value, time FROM job_metrics WHERE job_id = $1")
            .bind(id)
            .fetch_all(&mut db)
            .await
            .unwrap();
    let count = rows.len();
    let rows: MetricRows = rows.into_iter().map(|(n, s, v, t)| ((n, s as u64), (v, t))).collect();
    assert_eq!(rows.len(), count, "no (name, step) row twice");
    StoppedJob {
        status,
        shown_step: shown_step as u64,
        checkpoint_step: checkpoint_step as u64,
        rows,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_graceful_restart_checkpoints_the_running_job_and_resumes_it() {
    let mut app = TestApp::spawn().await;
    let (u, n) = upload_grid(&app).await;
    // Endless, so both stops land mid-run whatever the build's speed. Checkpoints only at
    // shutdown: the resume can only come from the shutdown checkpoint.
    let mut config = small_config(ENDLESS_ITERATIONS, 2);
    config["discriminator_iterations"] = json!(300);
    let job = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": config, "runner": {"log_every": 10, "checkpoint_every": 100_000_000}}),
    )
    .await;
    let id = job["id"].as_str().unwrap().to_owned();
    let before = wait_for_job(&app.client, &app.base_url, &id, Duration::from_secs(300), |j| {
        j["status"] == "running" && j["progress"]["step"].as_u64().unwrap() >= 100
    })
    .await;
    // A dataset a running job uses cannot be deleted.
    let delete = app.delete(&format!("/v1/datasets/{u}")).send().await.unwrap();
    assert_error(delete, StatusCode::CONFLICT, "dataset_in_use").await;
    let recorded_up_to = |step: u64| (1..=step / 10).map(|k| k * 10).collect::<Vec<u64>>();
    let steps_of = |rows: &MetricRows| {
        let steps: std::collections::BTreeSet<u64> = rows.keys().map(|(_, step)| *step).collect();
        steps.into_iter().collect::<Vec<u64>>()
    };

    app.stop().await;
    let first = stopped_job(&app, &id).await;
    let stopped_at = first.checkpoint_step;
    assert_eq!(first.status, "queued", "handed back to the queue");
    assert!(stopped_at >= before["progress"]["step"].as_u64().unwrap());
    assert_eq!(steps_of(&first.rows), recorded_up_to(stopped_at), "no recorded step lost");

    app.restart().await;
    let lowest = std::cell::Cell::new(u64::MAX);
    wait_for_job(&app.client, &app.base_url, &id, Duration::from_secs(300), |j| {
        let step = j["progress"]["step"].as_u64().unwrap();
        if j["status"] == "running" {
            lowest.set(lowest.get().min(step));
        }
        j["status"] == "running" && step >= stopped_at + 100
    })
    .await;

    app.stop().await;
    let second = stopped_job(&app, &id).await;
    assert_eq!(second.status, "queued");
    assert!(second.checkpoint_step >= stopped_at + 100, "{}", second.checkpoint_step);
    let expected_steps = recorded_up_to(second.checkpoint_step);
    assert_eq!(steps_of(&second.rows), expected_steps, "no recorded step lost");
    // The rows of the first run are the ones it wrote, time included: the resumed run did not
    // recompute them, so it started at the shutdown checkpoint, not before.
    let kept: MetricRows =
        second.rows.into_iter().filter(|((_, step), _)| *step <= stopped_at).collect();
    assert_eq!(kept, first.rows, "the first run's rows were rewritten");
    // What polling saw agrees: a claimed job shows its last reported step until the resumed
    // run's first report (its checkpoint's step); a resume from 0 would likely show 0.
    let floor = first.shown_step.min(stopped_at);
    assert!(lowest.get() >= floor, "seen running at {} < {floor}", lowest.get());
}
