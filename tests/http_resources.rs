//! The service's resources through the real server: a job is refused before it is queued when
//! its estimated memory is above `--max-job-memory`.

mod common;
mod jobs_support;

use common::{assert_error, TestApp};
use jobs_support::*;
use reqwest::StatusCode;
use serde_json::{json, Value};

fn safedice_job(u: &str, n: &str, config: Value) -> Value {
    json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
           "config": config})
}

#[tokio::test]
async fn a_job_estimated_above_max_job_memory_is_refused_before_it_is_queued() {
    let app = TestApp::spawn_with(|c| c.max_job_memory = 512 << 20).await;
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;

    // Batch 65536 with the default networks: SafeDICE's step buffers alone are over 3 GiB.
    let big = safedice_job(&u, &n, json!({"iterations": 100, "batch_size": 65_536}));
    let response = app.post("/v1/jobs").json(&big).send().await.unwrap();
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "job_too_large").await;
    assert!(message.contains("an estimated 3."), "names the estimate: {message}");
    assert!(message.contains("GiB"), "{message}");
    assert!(
        message.contains("limit of 512.0 MiB (536870912 bytes) (--max-job-memory)"),
        "{message}"
    );
    assert!(message.contains("batch_size"), "says what to lower: {message}");
    assert_eq!(app.count_rows("jobs").await, 0, "nothing was queued");

    // Wide networks count too, for every algorithm.
    let wide = json!({"algorithm": "bc", "unlabeled_dataset": u,
                      "config": {"batch_size": 4096, "hidden_sizes": [4096, 4096, 4096, 4096]}});
    let response = app.post("/v1/jobs").json(&wide).send().await.unwrap();
    assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "job_too_large").await;
    assert_eq!(app.count_rows("jobs").await, 0, "nothing was queued");

    // An unknown dataset is still a 404, whatever the configuration.
    let missing = safedice_job("no-such-dataset", &n, json!({"batch_size": 65_536}));
    let response = app.post("/v1/jobs").json(&missing).send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;

    // The same job with the default batch fits and is queued.
    let fits = safedice_job(&u, &n, json!({"iterations": 100}));
    let job = create_job(&app.client, &app.base_url, fits).await;
    assert_eq!(job["config"]["batch_size"], 512);
    assert_eq!(app.count_rows("jobs").await, 1);
}

#[tokio::test]
async fn the_default_limit_admits_default_jobs_and_refuses_far_larger_ones() {
    let app = TestApp::spawn().await;
    assert_eq!(app.config.max_job_memory, 4 << 30);
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;
    let huge = safedice_job(&u, &n, json!({"batch_size": 65_536, "hidden_sizes": [1024, 1024]}));
    let response = app.post("/v1/jobs").json(&huge).send().await.unwrap();
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "job_too_large").await;
    assert!(message.contains("limit of 4.0 GiB"), "{message}");
    assert_eq!(app.count_rows("jobs").await, 0);
    create_job(&app.client, &app.base_url, safedice_job(&u, &n, json!({"iterations": 100}))).await;
}
