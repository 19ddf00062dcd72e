//! Concurrent writers through the real server: clients that submit, cancel, upload and delete at
//! the same time as the workers train must only ever see the answers of a consistent state,
//! never a 5xx (a lock SQLite could not upgrade used to surface as 500 "database is locked"),
//! and a job is never accepted for a dataset deleted at the same moment.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::support::app::TestApp;
use crate::support::jobs::*;
use reqwest::{Response, StatusCode};
use serde_json::{json, Value};

/// Answers seen, by request kind and status, for the failure message and the test's log.
#[derive(Default)]
struct Tally(Mutex<BTreeMap<(&'static str, u16), usize>>);

impl Tally {
    /// Records `response` under `kind` and checks its status is one of `allowed`.
    async fn check(&self, kind: &'static str, response: Response, allowed: &[StatusCode]) -> Value {
        let status = response.status();
        *self.0.lock().unwrap().entry((kind, status.as_u16())).or_default() += 1;
        let body: Value = response.json().await.unwrap_or(Value::Null);
        assert!(
            allowed.contains(&status),
            "{kind}: unexpected {status} (allowed {allowed:?}): {body}\nso far: {:?}",
            self.0.lock().unwrap()
        );
        body
    }

    fn total(&self) -> usize {
        self.0.lock().unwrap().values().sum()
    }
}

/// A job of a few dozen tiny steps that checkpoints after every step: the workers write to the
/// database as often as they can, which is what the API's writers contend with.
fn churn_job(u: &str, n: &str, iterations: u64) -> Value {
    json!({
        "algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
        "config": {"iterations": iterations, "seed": 0, "hidden_sizes": [8], "batch_size": 16},
        "runner": {"log_every": 5, "checkpoint_every": 1},
    })
}

/// `dataset` as the bytes of an NPZ upload.
fn npz_bytes(dataset: &safedice::data::Dataset) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("data.npz");
    safedice::data::write_npz(dataset, &path).unwrap();
    std::fs::read(&path).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_submits_cancels_uploads_and_deletes_never_answer_5xx() {
    const TASKS: usize = 8;
    const ROUNDS: usize = 40;
    // Every task uploads from the same address, which holds half the upload slots: enough
    // slots that the cap never answers (this test is about the database's writers).
    let app = Arc::new(
        TestApp::spawn_with(|c| {
            c.workers = 2;
            c.max_concurrent_uploads = 2 * TASKS as u16;
        })
        .await,
    );
    let (u, n) = {
        let (unlabeled, non_preferred) = grid_datasets();
        let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
        let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;
        (u, n)
    };
    // A long job keeps one worker writing a checkpoint per step throughout, and keeps the shared
    // datasets in use (their deletes must answer 409, never go through).
    let anchor = create_job(&app.client, &app.base_url, churn_job(&u, &n, 10_000_000)).await;
    let anchor_id = anchor["id"].as_str().unwrap().to_owned();
    wait_for_status(&app.client, &app.base_url, &anchor_id, "running").await;
    let spare = npz_bytes(&grid_datasets().1);

    let tally = Arc::new(Tally::default());
    let jobs = Arc::new(Mutex::new(Vec::<String>::new()));
    let mut tasks = Vec::new();
    for task in 0..TASKS {
        let (app, tally, jobs) = (app.clone(), tally.clone(), jobs.clone());
        let (u, n, spare) = (u.clone(), n.clone(), spare.clone());
        tasks.push(tokio::spawn(async move {
            for round in 0..ROUNDS {
                let response = app.post("/v1/jobs").json(&churn_job(&u, &n, 30)).send().await;
                let job = tally.check("submit", response.unwrap(), &[StatusCode::CREATED]).await;
                let id = job["id"].as_str().unwrap().to_owned();
                jobs.lock().unwrap().push(id.clone());
                // Cancel the new job at once on even rounds (queued, or just claimed), and an
                // earlier job of any task on odd ones (queued, running or finished).
                let target = if round % 2 == 0 {
                    id
                } else {
                    let jobs = jobs.lock().unwrap();
                    jobs[(task * 7 + round * 13) % jobs.len()].clone()
                };
                let ok_or_finished = [StatusCode::OK, StatusCode::CONFLICT];
                let response = app.post(&format!("/v1/jobs/{target}/cancel")).send().await;
                tally.check("cancel", response.unwrap(), &ok_or_finished).await;
                let response = app.delete(&format!("/v1/datasets/{u}")).send().await;
                tally.check("delete in use", response.unwrap(), &[StatusCode::CONFLICT]).await;
                let name = format!("spare-{task}-{round}");
                let response = app.upload_dataset("spare.npz", spare.clone(), Some(&name)).await;
                let created = tally.check("upload", response, &[StatusCode::CREATED]).await;
                let spare_id = created["id"].as_str().unwrap();
                let response = app.delete(&format!("/v1/datasets/{spare_id}")).send().await;
                tally.check("delete unused", response.unwrap(), &[StatusCode::NO_CONTENT]).await;
                let response = app.get("/v1/jobs?limit=5").send().await;
                tally.check("list", response.unwrap(), &[StatusCode::OK]).await;
            }
        }));
    }
    for task in tasks {
        task.await.expect("a client task failed");
    }
    let response = app.post(&format!("/v1/jobs/{anchor_id}/cancel")).send().await.unwrap();
    tally.check("cancel", response, &[StatusCode::OK]).await;

    // Every job ends cancelled or succeeded: none failed for a write that lost a lock race.
    let ids = jobs.lock().unwrap().clone();
    for id in ids.iter().chain([&anchor_id]) {
        let job = wait_for_job(&app.client, &app.base_url, id, Duration::from_secs(300), |job| {
            ["succeeded", "cancelled"].contains(&job["status"].as_str().unwrap())
        })
        .await;
        assert!(job["error"].is_null(), "{job}");
    }
    assert_eq!(app.count_rows("datasets").await, 2, "only the shared datasets remain");
    eprintln!("{} requests from {TASKS} clients: {:?}", tally.total(), tally.0.lock().unwrap());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_submit_racing_a_delete_of_its_dataset_is_either_queued_or_refused() {
    const RACES: u64 = 60;
    let app = TestApp::spawn().await;
    let (unlabeled, non_preferred) = grid_datasets();
    let (unlabeled, non_preferred) = (npz_bytes(&unlabeled), npz_bytes(&non_preferred));
    let (mut accepted, mut deleted) = (0, 0);
    let mut refusals = BTreeMap::<String, usize>::new();
    for race in 0..RACES {
        let u = app.create_dataset("u.npz", unlabeled.clone()).await;
        let n = app.create_dataset("n.npz", non_preferred.clone()).await;
        // Alternate which of the two datasets is deleted, and land the delete at different
        // points of the submit (which reads both datasets before it queues the job).
        let victim = if race % 2 == 0 { &u } else { &n };
        // A job far too long to finish during the race: while it is queued or running its
        // datasets cannot be deleted.
        let submit = app.post("/v1/jobs").json(&churn_job(&u, &n, 1_000_000)).send();
        let delete = async {
            tokio::time::sleep(Duration::from_micros(race / 2 % 10 * 150)).await;
            app.delete(&format!("/v1/datasets/{victim}")).send().await
        };
        let (submit, delete) = tokio::join!(submit, delete);
        let (submit, delete) = (submit.unwrap(), delete.unwrap());
        let (submitted, delete_status) = (submit.status(), delete.status());
        let submit_body: Value = submit.json().await.unwrap();
        let delete_body: Value = delete.json().await.unwrap_or(Value::Null);
        let outcome = format!(
            "race {race}: submit {submitted} {submit_body}, delete {delete_status} {delete_body}"
        );
        let dataset = app.get(&format!("/v1/datasets/{victim}")).send().await.unwrap().status();
        let mut db = app.db().await;
        let jobs_using: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM jobs WHERE unlabeled_dataset_id = $1 OR non_preferred_dataset_id = $1",
        )
        .bind(victim)
        .fetch_one(&mut db)
        .await
        .unwrap();
        match (submitted, delete_status) {
            (StatusCode::CREATED, StatusCode::CONFLICT) => {
                assert_eq!(delete_body["error"]["code"], "dataset_in_use", "{outcome}");
                assert_eq!((dataset, jobs_using), (StatusCode::OK, 1), "{outcome}");
                accepted += 1;
                // The job is not what this test is about: stop it so the races stay light.
                let id = submit_body["id"].as_str().unwrap();
                let response = app.post(&format!("/v1/jobs/{id}/cancel")).send().await.unwrap();
                assert_eq!(response.status(), StatusCode::OK, "{outcome}");
            }
            (
                StatusCode::NOT_FOUND | StatusCode::CONFLICT | StatusCode::UNPROCESSABLE_ENTITY,
                StatusCode::NO_CONTENT,
            ) => {
                assert_eq!((dataset, jobs_using), (StatusCode::NOT_FOUND, 0), "{outcome}");
                assert!(
                    submit_body["error"]["message"].as_str().unwrap().contains(victim.as_str()),
                    "{outcome}"
                );
                deleted += 1;
                let code = submit_body["error"]["code"].as_str().unwrap().to_owned();
                *refusals.entry(format!("{submitted} {code}")).or_default() += 1;
            }
            _ => panic!("an inconsistent outcome: {outcome}"),
        }
        assert_eq!(app.stored_dataset_bytes().await, app.count_rows("datasets").await as usize);
    }
    // Never a job whose dataset is gone.
    let mut db = app.db().await;
    let orphans: i64 = sqlx::query_scalar(
        "SELECT COUNT(*) FROM jobs WHERE unlabeled_dataset_id NOT IN (SELECT id FROM datasets) \
         OR non_preferred_dataset_id NOT IN (SELECT id FROM datasets)",
    )
    .fetch_one(&mut db)
    .await
    .unwrap();
    assert_eq!(orphans, 0);
    eprintln!("{RACES} races: {accepted} jobs queued (delete refused), {deleted} datasets deleted (submit refused: {refusals:?})");
}
