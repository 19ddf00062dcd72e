//! Helpers of the job and policy tests: small datasets uploaded through the real API, jobs
//! queued and polled over HTTP. The data is the training core's gridworld
//! (tests/support/tasks.rs), written with the library's own NPZ writer.

use std::time::{Duration, Instant};

use reqwest::{Client, StatusCode};
use serde_json::{json, Value};

use super::tasks;

use safedice::data::Dataset;

/// Observation width of the gridworld (one-hot cells).
pub const GRID_OBS_DIM: usize = tasks::GRID_CELLS;

/// A small network config: jobs of a few hundred steps take seconds in a debug build.
pub fn small_config(iterations: u64, seed: u64) -> Value {
    json!({"iterations": iterations, "seed": seed, "hidden_sizes": [32, 32], "batch_size": 64})
}

/// Iterations of a job a test interrupts (kill, restart, cancel) or must see running: the API's
/// maximum, far more steps than any test waits for (a few thousand), so the interruption lands
/// mid-run whatever the build's speed. A job of a few thousand iterations instead finishes
/// between two progress reports on a fast build, and the interruption then tests nothing.
/// Such jobs never end by themselves: a test stops them and checks them at a checkpoint.
pub const ENDLESS_ITERATIONS: u64 = 100_000_000;

/// The gridworld's unlabeled (40 safe + 60 unsafe episodes) and non-preferred (20 unsafe) sets.
pub fn grid_datasets() -> (Dataset, Dataset) {
    (tasks::grid_dataset(40, 60, 3), tasks::grid_dataset(0, 20, 1003))
}

/// Uploads `dataset` as NPZ through `POST /v1/datasets`; returns its id.
pub async fn upload(client: &Client, base_url: &str, dataset: &Dataset, name: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(format!("{name}.npz"));
    safedice::data::write_npz(dataset, &path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let form = reqwest::multipart::Form::new()
        .part("file", reqwest::multipart::Part::bytes(bytes).file_name(format!("{name}.npz")))
        .text("name", name.to_owned());
    let response =
        client.post(format!("{base_url}/v1/datasets")).multipart(form).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::CREATED, "upload {name}");
    let body: Value = response.json().await.unwrap();
    body["id"].as_str().unwrap().to_owned()
}

/// `POST /v1/jobs`; asserts 201 and returns the job.
pub async fn create_job(client: &Client, base_url: &str, body: Value) -> Value {
    let response = client.post(format!("{base_url}/v1/jobs")).json(&body).send().await.unwrap();
    let status = response.status();
    let job: Value = response.json().await.unwrap();
    assert_eq!(status, StatusCode::CREATED, "create job: {job}");
    assert_eq!(job["status"], "queued");
    job
}

pub async fn get_json(client: &Client, url: &str) -> Value {
    let response = client.get(url).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK, "GET {url}");
    response.json().await.unwrap()
}

/// Polls the job until `done(job)` holds; panics after `timeout`.
pub async fn wait_for_job(
    client: &Client,
    base_url: &str,
    id: &str,
    timeout: Duration,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let started = Instant::now();
    loop {
        let job = get_json(client, &format!("{base_url}/v1/jobs/{id}")).await;
        if done(&job) {
            return job;
        }
        assert!(started.elapsed() < timeout, "job {id} did not get there in time: {job}");
        assert!(job["status"] != "failed", "job {id} failed: {job}");
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// Polls the job until it reaches `status`.
pub async fn wait_for_status(client: &Client, base_url: &str, id: &str, status: &str) -> Value {
    wait_for_job(client, base_url, id, Duration::from_secs(300), |job| job["status"] == status)
        .await
}

/// Polls the evaluation at `location` (`/v1/evaluations/<id>`) until it succeeds; panics if it
/// fails or takes over two minutes.
pub async fn wait_for_evaluation(client: &Client, base_url: &str, location: &str) -> Value {
    let started = Instant::now();
    loop {
        let evaluation = get_json(client, &format!("{base_url}{location}")).await;
        match evaluation["status"].as_str().unwrap() {
            "succeeded" => return evaluation,
            "failed" => panic!("evaluation failed: {evaluation}"),
            _ => {}
        }
        assert!(started.elapsed() < Duration::from_secs(120), "evaluation stuck: {evaluation}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Every grid cell as a one-hot observation.
pub fn grid_observations() -> Vec<Vec<f32>> {
    (0..GRID_OBS_DIM)
        .map(|cell| (0..GRID_OBS_DIM).map(|i| (i == cell) as u8 as f32).collect())
        .collect()
}

/// Six-rooms demonstrations (the env's own demonstrators) uploaded through the API.
pub async fn upload_six_rooms(client: &Client, base_url: &str) -> (String, String) {
    let spec = safedice::envs::DatagenSpec {
        env: "six-rooms".into(),
        preferred: 20,
        non_preferred: 30,
        labeled: 10,
        seed: 0,
    };
    let generated = safedice::envs::generate(&spec).unwrap();
    let u = upload(client, base_url, &generated.unlabeled, "rooms-unlabeled").await;
    let n = upload(
        client,
        base_url,
        generated.labeled_non_preferred.as_ref().unwrap(),
        "rooms-labeled",
    )
    .await;
    (u, n)
}
