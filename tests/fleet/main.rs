//! The service as a fleet on PostgreSQL: a `safedice serve --workers 0` API node and
//! `safedice worker` processes, each with a data directory of its own (nothing shared but the
//! database), on a throwaway cluster (`support::postgres`). Workers are killed (SIGKILL),
//! paused past their lease (SIGSTOP) and cancelled through the API node; the tests read the
//! outcome over HTTP and from the database.
//!
//! Without PostgreSQL's binaries every test here skips with a loud message (CI sets
//! `SAFEDICE_REQUIRE_POSTGRES=1`, which makes that a failure).

#[path = "../support"]
mod support {
    #[allow(dead_code)]
    pub mod jobs;
    pub mod postgres;
    #[allow(dead_code)]
    pub mod tasks;
}

mod models;
mod process;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use futures::StreamExt;
use reqwest::StatusCode;
use serde_json::{json, Value};
use sqlx::{AnyConnection, Connection, PgConnection};

use process::Fleet;
use safedice::domain::RetryBackoff;
use safedice::store::Store;
use support::jobs::{
    create_job, get_json, grid_datasets, upload, wait_for_status, ENDLESS_ITERATIONS,
};

/// A job body on the gridworld data: SafeDICE with small networks, `iterations` long. Its 50
/// discriminator steps cannot always tell D^N from D^U, so the uniform fallback is off: every
/// job then runs (and records) the same main loop, which the checks on metric rows rely on.
fn job(unlabeled: &str, non_preferred: &str, iterations: u64, seed: u64) -> Value {
    json!({
        "algorithm": "safedice",
        "unlabeled_dataset": unlabeled,
        "non_preferred_dataset": non_preferred,
        "config": {"iterations": iterations, "seed": seed, "hidden_sizes": [32, 32],
                   "batch_size": 64, "discriminator_iterations": 50, "uniform_fallback": false},
        "runner": {"log_every": 10, "checkpoint_every": 100},
    })
}

async fn upload_grid(fleet: &Fleet) -> (String, String) {
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&fleet.client, &fleet.api_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&fleet.client, &fleet.api_url, &non_preferred, "grid-non-preferred").await;
    (u, n)
}

async fn db(fleet: &Fleet) -> PgConnection {
    PgConnection::connect(&fleet.database_url).await.unwrap()
}

/// Either database, for the checks both backends answer alike (`$1` parameters).
async fn any_db(fleet: &Fleet) -> AnyConnection {
    sqlx::any::install_default_drivers();
    AnyConnection::connect(&fleet.database_url).await.unwrap()
}

/// One clock for every stored time: the workers' metric samples (taken on the worker's clock,
/// moved onto the database's when written) and log lines lie between their job's start and end
/// (stamped on the database's clock). The slack covers the round trip the offset is measured
/// over; a unit or sign slip in it would put samples seconds to hours away.
async fn every_sample_and_log_line_within_its_run(conn: &mut AnyConnection) {
    let times = "SELECT x.time, j.started_at, j.finished_at FROM jobs AS j JOIN \
                   (SELECT job_id, time FROM job_metrics UNION ALL SELECT job_id, time FROM job_logs) \
                 AS x ON x.job_id = j.id";
    let rows: Vec<(String, String, String)> =
        sqlx::query_as(times).fetch_all(&mut *conn).await.unwrap();
    assert!(!rows.is_empty());
    let parse = |t: &str| chrono::DateTime::parse_from_rfc3339(t).unwrap();
    let slack = chrono::TimeDelta::milliseconds(50);
    for (time, started, finished) in &rows {
        let (time, started, finished) = (parse(time), parse(started), parse(finished));
        assert!(
            started - slack <= time && time <= finished + slack,
            "{time} outside {started}..{finished}"
        );
    }
}

/// Waits until the job is running with a checkpoint stored: a kill then lands mid-run, and the
/// job has something to resume from.
async fn wait_for_checkpoint(fleet: &Fleet, id: &str) -> Value {
    let started = Instant::now();
    let mut conn = db(fleet).await;
    loop {
        let step: Option<i64> =
            sqlx::query_scalar("SELECT step FROM job_checkpoints WHERE job_id = $1")
                .bind(id)
                .fetch_optional(&mut conn)
                .await
                .unwrap();
        let job = get_json(&fleet.client, &format!("{}/v1/jobs/{id}", fleet.api_url)).await;
        assert_ne!(job["status"], "succeeded", "the job ended before the test could stop it");
        if step.is_some() && job["status"] == "running" {
            return job;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "no checkpoint: {job}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

async fn weights(fleet: &Fleet, job: &Value) -> Vec<u8> {
    let policy = job["policy_id"].as_str().expect("a succeeded job has a policy");
    let url = format!("{}/v1/policies/{policy}/weights", fleet.api_url);
    let response = fleet.client.get(url).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    response.bytes().await.unwrap().to_vec()
}

#[tokio::test]
async fn three_workers_run_twelve_jobs_each_exactly_once() {
    let Some(fleet) = Fleet::start(3).await else { return };
    let by_worker = twelve_jobs_each_exactly_once(&fleet).await;
    // A notification wakes every idle worker at each submit, so all of them claim.
    assert!(by_worker.len() >= 2, "the work spread over the workers: {by_worker:?}");
}

/// Several processes of one machine may share one SQLite data directory with the same leases.
#[tokio::test]
async fn three_workers_sharing_one_sqlite_file_run_twelve_jobs_each_exactly_once() {
    // No notifications on SQLite: idle workers look every 2 s, and one busy worker may take
    // every short job before the others look, so how the work spreads is not asserted here.
    twelve_jobs_each_exactly_once(&Fleet::start_sqlite(3).await).await;
}

/// Queues 12 short jobs and checks each ran exactly once; the jobs each worker ran.
async fn twelve_jobs_each_exactly_once(fleet: &Fleet) -> BTreeMap<String, usize> {
    let (u, n) = upload_grid(fleet).await;
    let mut ids = Vec::new();
    for seed in 0..12 {
        let created = create_job(&fleet.client, &fleet.api_url, job(&u, &n, 200, seed)).await;
        ids.push(created["id"].as_str().unwrap().to_owned());
    }
    let mut by_worker: BTreeMap<String, usize> = BTreeMap::new();
    for id in &ids {
        let done = wait_for_status(&fleet.client, &fleet.api_url, id, "succeeded").await;
        *by_worker.entry(done["worker"].as_str().unwrap().to_owned()).or_default() += 1;
    }
    let mut conn = any_db(fleet).await;
    let policies: Vec<(String, i64)> =
        sqlx::query_as("SELECT job_id, COUNT(*) FROM policies GROUP BY job_id ORDER BY job_id")
            .fetch_all(&mut conn)
            .await
            .unwrap();
    assert_eq!(policies.len(), 12, "one policy per job: {policies:?}");
    assert!(policies.iter().all(|(_, count)| *count == 1), "{policies:?}");
    // Every job logs the same steps: a duplicated or lost row would change one job's count.
    let rows: Vec<i64> =
        sqlx::query_scalar("SELECT COUNT(*) FROM job_metrics GROUP BY job_id ORDER BY job_id")
            .fetch_all(&mut conn)
            .await
            .unwrap();
    assert_eq!(rows.len(), 12);
    assert!(rows.iter().all(|&count| count == rows[0] && count > 0), "metric rows: {rows:?}");
    let takeovers: i64 =
        sqlx::query_scalar("SELECT CAST(SUM(lease_takeovers) AS BIGINT) FROM jobs")
            .fetch_one(&mut conn)
            .await
            .unwrap();
    assert_eq!(takeovers, 0, "no worker died, so no job changed hands");
    every_sample_and_log_line_within_its_run(&mut conn).await;
    eprintln!("jobs per worker: {by_worker:?}");
    by_worker
}

#[tokio::test]
async fn a_killed_workers_job_is_finished_by_another_with_the_same_weights() {
    let Some(mut fleet) = Fleet::start(2).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let mut body = job(&u, &n, 3000, 7);
    // On two threads: the taker-over computes the job's shards as the first worker did.
    body["config"]["threads"] = json!(2);
    let interrupted = create_job(&fleet.client, &fleet.api_url, body.clone()).await;
    let id = interrupted["id"].as_str().unwrap();
    let running = wait_for_checkpoint(&fleet, id).await;
    let victim = running["worker"].as_str().unwrap().to_owned();
    fleet.kill_worker(&victim);

    let done = wait_for_status(&fleet.client, &fleet.api_url, id, "succeeded").await;
    assert_ne!(done["worker"], victim.as_str(), "another worker finished it");
    let mut conn = db(&fleet).await;
    let takeovers: i64 = sqlx::query_scalar("SELECT lease_takeovers FROM jobs WHERE id = $1")
        .bind(id)
        .fetch_one(&mut conn)
        .await
        .unwrap();
    assert_eq!(takeovers, 1);
    let metrics = fleet.client.get(format!("{}/metrics", fleet.api_url)).send().await.unwrap();
    let metrics = metrics.text().await.unwrap();
    assert!(metrics.lines().any(|l| l == "safedice_lease_takeovers 1"), "{metrics}");

    // The same job again, uninterrupted, on the surviving worker.
    let again = create_job(&fleet.client, &fleet.api_url, body).await;
    let again =
        wait_for_status(&fleet.client, &fleet.api_url, again["id"].as_str().unwrap(), "succeeded")
            .await;
    assert_eq!(weights(&fleet, &done).await, weights(&fleet, &again).await, "bit for bit");
}

/// Polls the job until `done` says so of it (two minutes at most).
async fn wait_for_job(fleet: &Fleet, id: &str, what: &str, done: impl Fn(&Value) -> bool) -> Value {
    let started = Instant::now();
    loop {
        let job = get_json(&fleet.client, &format!("{}/v1/jobs/{id}", fleet.api_url)).await;
        if done(&job) {
            return job;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "never {what}: {job}");
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// The poison job: every worker that claims it is killed (SIGKILL, what the kernel's
/// out-of-memory killer sends). While no worker is left the job shows that its lease expired;
/// the next worker queues it again for after the backoff; at its `max_attempts` it is discarded
/// with the history of its attempts instead of killing workers for ever.
#[tokio::test]
async fn a_job_that_kills_every_worker_is_discarded_after_its_max_attempts() {
    let Some(mut fleet) = Fleet::start(1).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let mut body = job(&u, &n, ENDLESS_ITERATIONS, 5);
    body["max_attempts"] = json!(2);
    let created = create_job(&fleet.client, &fleet.api_url, body).await;
    let id = created["id"].as_str().unwrap();
    assert_eq!((created["attempt"].as_u64(), created["max_attempts"].as_u64()), (Some(0), Some(2)));
    let mut victims = Vec::new();
    let mut killed_at = 0;
    for attempt in 1..=2u64 {
        // Past the step the last attempt was killed at: this attempt's worker has claimed the
        // job, logged it and trained (the row keeps the last attempt's step until then).
        let running = wait_for_job(&fleet, id, "running", |job| {
            job["status"] == "running"
                && job["attempt"] == attempt
                && job["progress"]["step"].as_u64().unwrap() > killed_at
        })
        .await;

        let victim = running["worker"].as_str().unwrap().to_owned();
        fleet.kill_worker(&victim);
        // No worker is left: the job says it waits for one, on the database's clock.
        let waiting =
            wait_for_job(&fleet, id, "lease expired", |job| job["lease_expired_at"].is_string())
                .await;
        assert_eq!(waiting["status"], "running");
        // Frozen where the killed worker last wrote it.
        killed_at = waiting["progress"]["step"].as_u64().unwrap();
        fleet.start_worker();
        victims.push(victim);
        if attempt == 1 {
            let queued =
                wait_for_job(&fleet, id, "queued again", |job| job["status"] != "running").await;
            assert_eq!(queued["status"], "queued", "{queued}");
            assert!(queued["retry_at"].is_string(), "the backoff shows: {queued}");
        }
    }
    let failed = wait_for_job(&fleet, id, "discarded", |job| job["status"] != "running").await;
    assert_eq!(failed["status"], "discarded", "out of attempts, not a failure of the code");
    let error = failed["error"].as_str().unwrap();
    assert!(
        error.starts_with("gave up after 2 attempts (2 ended with the worker gone)"),
        "{error}"
    );
    assert!(error.contains("out-of-memory killer") && error.contains("GiB of memory"), "{error}");
    assert_eq!((failed["attempt"].as_u64(), &failed["policy_id"]), (Some(2), &Value::Null));

    let url = format!("{}/v1/jobs/{id}/attempts", fleet.api_url);
    let attempts = get_json(&fleet.client, &url).await;
    let attempts = attempts["attempts"].as_array().unwrap().clone();
    let seen: Vec<(u64, &str, &str)> = attempts
        .iter()
        .map(|a| {
            let worker = a["worker"].as_str().unwrap();
            (a["attempt"].as_u64().unwrap(), worker, a["outcome"].as_str().unwrap())
        })
        .collect();
    let expected: Vec<(u64, &str, &str)> =
        victims.iter().zip(1..).map(|(w, n)| (n, w.as_str(), "crashed")).collect();
    assert_eq!(seen, expected);
    let mut conn = db(&fleet).await;
    let (takeovers, checkpoints): (i64, i64) = sqlx::query_as(
        "SELECT lease_takeovers, (SELECT COUNT(*) FROM job_checkpoints WHERE job_id = $1) \
         FROM jobs WHERE id = $1",
    )
    .bind(id)
    .fetch_one(&mut conn)
    .await
    .unwrap();
    assert_eq!((takeovers, checkpoints), (2, 0));
    // The job's log tells the story: each claim, the retry with its wait, the end.
    let logs = get_json(&fleet.client, &format!("{}/v1/jobs/{id}/logs", fleet.api_url)).await;
    let messages: Vec<&str> =
        logs.as_array().unwrap().iter().map(|l| l["message"].as_str().unwrap()).collect();
    let has = |prefix: &str| messages.iter().filter(|m| m.starts_with(prefix)).count();
    assert_eq!(has("claimed by worker"), 2, "{messages:?}");
    assert_eq!(has("attempt 1 of 2 ended: worker "), 1, "{messages:?}");
    assert_eq!(messages.last(), Some(&error), "{messages:?}");
}

/// Every database connection of the fleet cut while a job runs (the server terminates their
/// backends, as a failover or an administrator does): the API node and the worker reconnect by
/// themselves, the job is kept or handed back and resumed, nothing is written twice, and it ends
/// with the weights and metrics of an uninterrupted run, still on its first attempt.
#[tokio::test]
async fn connections_cut_by_the_database_mid_run_lose_nothing_and_write_nothing_twice() {
    let Some(fleet) = Fleet::start(1).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let body = job(&u, &n, 3000, 13);
    let created = create_job(&fleet.client, &fleet.api_url, body.clone()).await;
    let id = created["id"].as_str().unwrap();
    wait_for_checkpoint(&fleet, id).await;
    let mut conn = db(&fleet).await;
    for _ in 0..3 {
        let cut: i64 = sqlx::query_scalar(
            "SELECT COUNT(*) FROM (SELECT pg_terminate_backend(pid) FROM pg_stat_activity \
             WHERE datname = current_database() AND pid <> pg_backend_pid()) AS cut",
        )
        .fetch_one(&mut conn)
        .await
        .unwrap();
        assert!(cut > 0, "the fleet holds connections");
        tokio::time::sleep(Duration::from_millis(400)).await;
    }
    let done = wait_for_status(&fleet.client, &fleet.api_url, id, "succeeded").await;
    assert_eq!(done["attempt"], 1, "a cut connection is not a crash: {done}");
    let url = format!("{}/v1/jobs/{id}/attempts", fleet.api_url);
    let attempts = get_json(&fleet.client, &url).await;
    let outcomes: Vec<&str> = attempts["attempts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["outcome"].as_str().unwrap())
        .collect();
    eprintln!("attempts after the cuts: {outcomes:?}");
    assert!(
        outcomes.last() == Some(&"succeeded")
            && outcomes.iter().rev().skip(1).all(|o| *o == "released"),
        "{outcomes:?}"
    );

    let again = create_job(&fleet.client, &fleet.api_url, body).await;
    let again =
        wait_for_status(&fleet.client, &fleet.api_url, again["id"].as_str().unwrap(), "succeeded")
            .await;
    assert_eq!(weights(&fleet, &done).await, weights(&fleet, &again).await, "bit for bit");
    let rows = |id: String| {
        let query = "SELECT name, step, value FROM job_metrics WHERE job_id = $1 \
                     ORDER BY name, step";
        sqlx::query_as::<_, (String, i64, f64)>(query).bind(id)
    };
    let interrupted = rows(id.to_owned()).fetch_all(&mut conn).await.unwrap();
    let uninterrupted =
        rows(again["id"].as_str().unwrap().to_owned()).fetch_all(&mut conn).await.unwrap();
    assert!(!interrupted.is_empty());
    assert!(interrupted == uninterrupted, "the same metric rows, each once, bit for bit");
}

/// PostgreSQL stopped for 20 s while two jobs train on two workers (its own cluster, so the
/// tests beside it keep theirs): meanwhile the API node answers 503 `database_unavailable`
/// (not `database_busy`), after the first such answer from the outage it then knows of, and
/// `/healthz` still answers; once it is back the processes reconnect by themselves (none is
/// restarted) and each job ends `succeeded` once, with the weights and the metric rows (each
/// step once) of an uninterrupted run of the same job.
#[tokio::test]
async fn postgres_stopped_for_twenty_seconds_mid_training_loses_and_duplicates_nothing() {
    let Some(cluster) = support::postgres::private_cluster() else { return };
    let fleet = Fleet::start_on_database(cluster.new_database().await, 2).await;
    let (u, n) = upload_grid(&fleet).await;
    let bodies = [job(&u, &n, 3000, 31), job(&u, &n, 3000, 32)];
    let mut ids = Vec::new();
    for body in &bodies {
        ids.push(
            create_job(&fleet.client, &fleet.api_url, body.clone()).await["id"]
                .as_str()
                .unwrap()
                .to_owned(),
        );
    }
    for id in &ids {
        wait_for_checkpoint(&fleet, id).await;
    }

    let stopped = Instant::now();
    cluster.stop();
    let url = format!("{}/v1/jobs/{}", fleet.api_url, ids[0]);
    let response = fleet.client.get(&url).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::SERVICE_UNAVAILABLE);
    let body: Value = response.json().await.unwrap();
    assert_eq!(body["error"]["code"], "database_unavailable", "{body}");
    // The outage is now known: the next requests are answered from it (without each waiting
    // for a pooled connection), and a route that needs no database still answers.
    let known = Instant::now();
    for _ in 0..3 {
        let response = fleet.client.get(&url).send().await.unwrap();
        assert_eq!(response.status(), StatusCode::SERVICE_UNAVAILABLE);
        let body: Value = response.json().await.unwrap();
        assert_eq!(body["error"]["code"], "database_unavailable", "{body}");
        let message = body["error"]["message"].as_str().unwrap();
        assert!(message.contains("found down"), "answered from the known outage: {message}");
    }
    eprintln!("first answer after {:?}, the next three in {:?}", known - stopped, known.elapsed());
    let health = fleet.client.get(format!("{}/healthz", fleet.api_url)).send().await.unwrap();
    assert_eq!(health.status(), StatusCode::OK, "no database needed");
    tokio::time::sleep(Duration::from_secs(20).saturating_sub(stopped.elapsed())).await;
    cluster.start_again();
    eprintln!("PostgreSQL was down for {:?}", stopped.elapsed());

    let mut done = Vec::new();
    for id in &ids {
        let job = wait_for_job(&fleet, id, "succeeded after the outage", |j| {
            ["succeeded", "failed", "cancelled", "discarded"]
                .contains(&j["status"].as_str().unwrap_or(""))
        })
        .await;
        assert_eq!(job["status"], "succeeded", "{job}");
        eprintln!("job {id}: attempt {} of {}", job["attempt"], job["max_attempts"]);
        done.push(job);
    }
    let mut conn = db(&fleet).await;
    let rows = |id: String| {
        let query =
            "SELECT name, step, value FROM job_metrics WHERE job_id = $1 ORDER BY name, step";
        sqlx::query_as::<_, (String, i64, f64)>(query).bind(id)
    };
    for (body, job) in bodies.into_iter().zip(&done) {
        let again = create_job(&fleet.client, &fleet.api_url, body).await;
        let again = wait_for_status(
            &fleet.client,
            &fleet.api_url,
            again["id"].as_str().unwrap(),
            "succeeded",
        )
        .await;
        assert_eq!(weights(&fleet, job).await, weights(&fleet, &again).await, "bit for bit");
        let interrupted =
            rows(job["id"].as_str().unwrap().to_owned()).fetch_all(&mut conn).await.unwrap();
        let uninterrupted =
            rows(again["id"].as_str().unwrap().to_owned()).fetch_all(&mut conn).await.unwrap();
        assert!(!interrupted.is_empty());
        assert!(interrupted == uninterrupted, "the same metric rows, each once, bit for bit");
        let policies: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM policies WHERE job_id = $1")
            .bind(job["id"].as_str().unwrap())
            .fetch_one(&mut conn)
            .await
            .unwrap();
        assert_eq!(policies, 1, "one policy per job");
    }
    let jobs: i64 =
        sqlx::query_scalar("SELECT COUNT(*) FROM jobs").fetch_one(&mut conn).await.unwrap();
    assert_eq!(jobs, 4, "no job lost or made twice");
}

/// A snapshot of everything stored for a job.
async fn stored(conn: &mut PgConnection, id: &str) -> (String, i64, f64, i64, i64) {
    let job: (String,) = sqlx::query_as(
        "SELECT CONCAT_WS('|', status, step, updated_at, lease_token, lease_owner, policy_id) \
         FROM jobs WHERE id = $1",
    )
    .bind(id)
    .fetch_one(&mut *conn)
    .await
    .unwrap();
    let (rows, sum): (i64, f64) = sqlx::query_as(
        "SELECT COUNT(*), COALESCE(SUM(value), 0) FROM job_metrics WHERE job_id = $1",
    )
    .bind(id)
    .fetch_one(&mut *conn)
    .await
    .unwrap();
    let checkpoints: i64 =
        sqlx::query_scalar("SELECT COUNT(*) FROM job_checkpoints WHERE job_id = $1")
            .bind(id)
            .fetch_one(&mut *conn)
            .await
            .unwrap();
    let policies: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM policies WHERE job_id = $1")
        .bind(id)
        .fetch_one(&mut *conn)
        .await
        .unwrap();
    (job.0, rows, sum, checkpoints, policies)
}

#[tokio::test]
async fn a_worker_paused_past_its_lease_writes_nothing_more_for_the_job() {
    let Some(mut fleet) = Fleet::start(1).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let created = create_job(&fleet.client, &fleet.api_url, job(&u, &n, 3000, 11)).await;
    let id = created["id"].as_str().unwrap();
    let running = wait_for_checkpoint(&fleet, id).await;
    let paused = running["worker"].as_str().unwrap().to_owned();
    fleet.signal_worker(&paused, "STOP");
    fleet.start_worker();
    let done = wait_for_status(&fleet.client, &fleet.api_url, id, "succeeded").await;
    assert_ne!(done["worker"], paused.as_str());

    let mut conn = db(&fleet).await;
    let before = stored(&mut conn, id).await;
    fleet.signal_worker(&paused, "CONT");
    // The paused worker wakes up mid-run, tries its next write, and is refused.
    fleet.wait_for_log(&paused, "another worker took the job over", Duration::from_secs(60)).await;
    let after = stored(&mut conn, id).await;
    assert_eq!(before, after, "the paused worker wrote nothing after waking up");
    assert_eq!(after.4, 1, "one policy");
    // Its attempt says what happened: first taken for a crash, then amended by the worker.
    let url = format!("{}/v1/jobs/{id}/attempts", fleet.api_url);
    let started = Instant::now();
    let outcomes = loop {
        let attempts = get_json(&fleet.client, &url).await;
        let outcomes: Vec<String> = attempts["attempts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| format!("{} {} {}", a["attempt"], a["worker"], a["outcome"]))
            .collect();
        if outcomes.first().is_some_and(|o| o.ends_with("\"lease_lost\"")) {
            break outcomes;
        }
        assert!(started.elapsed() < Duration::from_secs(30), "{outcomes:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let winner = done["worker"].as_str().unwrap();
    let expected =
        [format!("1 \"{paused}\" \"lease_lost\""), format!("2 \"{winner}\" \"succeeded\"")];
    assert_eq!(outcomes, expected);
}

#[tokio::test]
async fn cancel_and_progress_cross_from_the_api_node_to_a_worker_process() {
    let Some(fleet) = Fleet::start(1).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let created =
        create_job(&fleet.client, &fleet.api_url, job(&u, &n, ENDLESS_ITERATIONS, 3)).await;
    let id = created["id"].as_str().unwrap();
    let events_url = format!("{}/v1/jobs/{id}/events", fleet.api_url);
    let mut events = EventReader::open(&fleet.client, &events_url).await;
    // The API node trains nothing: this progress comes from the worker process.
    let progress = events.next_named("progress").await;
    assert!(progress["step"].as_u64().unwrap() > 0, "{progress}");
    // Its log follower, fed by the events relayed from the worker, sees the worker's lines.
    let logs_url = format!("{}/v1/jobs/{id}/logs?follow=true", fleet.api_url);
    let mut logs = EventReader::open(&fleet.client, &logs_url).await;
    let claimed = logs.next_named("log").await;
    assert!(claimed["message"].as_str().unwrap().starts_with("claimed by worker"), "{claimed}");

    let asked = Instant::now();
    let response =
        fleet.client.post(format!("{}/v1/jobs/{id}/cancel", fleet.api_url)).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    loop {
        let status = events.next_named("status").await;
        if status["status"] == "cancelled" {
            break;
        }
        assert_eq!(status["status"], "running", "{status}");
    }
    eprintln!("cancel reached the worker and came back in {:?}", asked.elapsed());
    // The follower ends after the worker's last line, which says it stopped.
    let mut last = claimed;
    while let Some(line) = logs.next_named_or_end("log").await {
        last = line;
    }
    assert!(last["message"].as_str().unwrap().starts_with("cancelled at step"), "{last}");
    let job = get_json(&fleet.client, &format!("{}/v1/jobs/{id}", fleet.api_url)).await;
    assert_eq!(job["status"], "cancelled");
    assert!(job["progress"]["step"].as_u64().unwrap() > 0);
}

/// Server-sent events of one stream, read as they come.
struct EventReader {
    body: futures::stream::BoxStream<'static, reqwest::Result<bytes::Bytes>>,
    buffer: String,
}

impl EventReader {
    async fn open(client: &reqwest::Client, url: &str) -> EventReader {
        let response = client.get(url).send().await.unwrap();
        assert_eq!(response.status(), StatusCode::OK);
        EventReader { body: response.bytes_stream().boxed(), buffer: String::new() }
    }

    /// The data of the next event called `name` (others are skipped); panics after a minute
    /// or if the stream ends first.
    async fn next_named(&mut self, name: &str) -> Value {
        self.next_named_or_end(name).await.expect("the stream ended")
    }

    /// The same, or None once the stream has ended.
    async fn next_named_or_end(&mut self, name: &str) -> Option<Value> {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            while let Some(end) = self.buffer.find("\n\n") {
                let event: String = self.buffer.drain(..end + 2).collect();
                let field = |key: &str| {
                    event
                        .lines()
                        .find_map(|l| l.strip_prefix(key))
                        .map(str::trim)
                        .map(str::to_owned)
                };
                if field("event:").as_deref() == Some(name) {
                    return Some(serde_json::from_str(&field("data:").unwrap()).unwrap());
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            let chunk = tokio::time::timeout(left, self.body.next())
                .await
                .unwrap_or_else(|_| panic!("no {name} event within a minute"))?
                .unwrap();
            self.buffer.push_str(&String::from_utf8_lossy(&chunk));
        }
    }
}

/// A worker stopped inside a transaction (SIGSTOP between two statements) holds its row lock
/// for as long as its connection lives, and claims skip locked rows: the store's sessions end a
/// transaction left idle, so the job is still taken over once the lease expired.
#[tokio::test]
async fn a_transaction_left_open_by_a_stalled_worker_does_not_block_the_takeover() {
    let Some(fleet) = Fleet::start(0).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let created = create_job(&fleet.client, &fleet.api_url, job(&u, &n, 100, 0)).await;
    let id = created["id"].as_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let stalled = Store::connect(dir.path(), Some(&fleet.database_url)).await.unwrap();
    let taker = Store::connect(dir.path(), Some(&fleet.database_url)).await.unwrap();
    let (_, lease) =
        stalled.claim_next_job("stalled", Duration::from_millis(500)).await.unwrap().unwrap();
    let mut open = stalled.begin_write().await.unwrap();
    let locked: Option<String> = sqlx::query_scalar("SELECT id FROM jobs WHERE id = $1 FOR UPDATE")
        .bind(lease.id.as_str())
        .fetch_optional(&mut *open)
        .await
        .unwrap();
    assert_eq!(locked.as_deref(), Some(id));

    let started = Instant::now();
    let taken = loop {
        // The reaper skips the locked row until the server ends the stalled transaction.
        taker.reap_expired_jobs("taker", &RetryBackoff::new(Duration::ZERO)).await.unwrap();
        if let Some((job, _)) =
            taker.claim_next_job("taker", Duration::from_secs(30)).await.unwrap()
        {
            break job;
        }
        assert!(started.elapsed() < Duration::from_secs(30), "the locked job was never taken over");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    eprintln!("taken over {:?} after the lock was taken", started.elapsed());
    assert_eq!((taken.id.as_str(), taken.worker.as_deref()), (id, Some("taker")));
    // The stalled transaction was ended by the server: nothing it does commits.
    let late =
        sqlx::query("UPDATE jobs SET step = 99 WHERE id = $1").bind(id).execute(&mut *open).await;
    assert!(late.is_err() || open.commit().await.is_err(), "the stalled transaction still commits");
    assert_eq!(taker.job(&taken.id).await.unwrap().step, 0);
}
