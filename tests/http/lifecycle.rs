//! A job's life beyond training: name, tags and notes (set, edited, searched), its log (listed
//! and followed), its metrics' names and CSV export, and deleting jobs, policies and
//! evaluations with their rules — each bad request with its exact status and nothing changed.

use std::time::Duration;

use crate::support::app::{assert_error, assert_v2_error, TestApp};
use crate::support::jobs::*;
use futures::StreamExt;
use reqwest::StatusCode;
use serde_json::{json, Value};

async fn bc_job(app: &TestApp, dataset: &str, extra: Value) -> Value {
    let mut body = json!({"algorithm": "bc", "unlabeled_dataset": dataset,
                          "config": small_config(60, 0), "runner": {"log_every": 10}});
    body.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
    create_job(&app.client, &app.base_url, body).await
}

/// The ids of a page's jobs, sorted (jobs created in the same millisecond list in id order).
fn ids(page: &Value) -> Vec<String> {
    let mut ids: Vec<String> = page["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_str().unwrap().into())
        .collect();
    ids.sort();
    ids
}

async fn patch(app: &TestApp, id: &str, body: Value) -> reqwest::Response {
    app.request(reqwest::Method::PATCH, &format!("/v1/jobs/{id}")).json(&body).send().await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn names_and_tags_are_set_edited_and_searched() {
    let app = TestApp::spawn_with(|c| c.workers = 0).await;
    let (unlabeled, _) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let a = bc_job(
        &app,
        &u,
        json!({"name": "  Baseline 50/50 ", "tags": ["env=grid", "bc", "bc"],
                                    "notes": "first try\nsecond line"}),
    )
    .await;
    assert_eq!(a["name"], "Baseline 50/50");
    assert_eq!(a["tags"], json!(["env=grid", "bc"]));
    assert_eq!(a["notes"], "first try\nsecond line");
    let b = bc_job(&app, &u, json!({"name": "under_score", "tags": ["env=grid"]})).await;
    let c = bc_job(&app, &u, json!({})).await;
    assert!(c["name"].is_null() && c["tags"] == json!([]) && c["notes"].is_null());
    let (a_id, b_id, c_id) =
        (a["id"].as_str().unwrap(), b["id"].as_str().unwrap(), c["id"].as_str().unwrap());

    let app = &app;
    let list = |query: &str| {
        let url = app.url(&format!("/v1/jobs?{query}"));
        async move { get_json(&app.client, &url).await }
    };
    let mut both = [a_id, b_id];
    both.sort();
    assert_eq!(ids(&list("tag=env%3Dgrid").await), both);
    assert_eq!(ids(&list("tag=bc").await), [a_id]);
    assert_eq!(ids(&list("tag=b").await), Vec::<String>::new(), "tags match whole");
    assert_eq!(ids(&list("q=BASELINE").await), [a_id], "names match in any case");
    // `_` and `%` are literal, not LIKE wildcards.
    assert_eq!(ids(&list("q=r_s").await), [b_id]);
    assert_eq!(ids(&list("q=%25").await), Vec::<String>::new());
    assert_eq!(ids(&list(&format!("q={}", &c_id[..8])).await), [c_id], "an id prefix");
    let page = list("tag=env%3Dgrid&status=queued&limit=1").await;
    assert_eq!((page["total"].as_u64(), page["next_offset"].as_u64()), (Some(2), Some(1)));

    // Merge patch: present keys replace (null clears), absent keys stay.
    let edited = patch(app, a_id, json!({"name": "renamed", "tags": ["x"]})).await;
    assert_eq!(edited.status(), StatusCode::OK);
    let edited: Value = edited.json().await.unwrap();
    assert_eq!((&edited["name"], &edited["tags"]), (&json!("renamed"), &json!(["x"])));
    assert_eq!(edited["notes"], "first try\nsecond line");
    let cleared: Value =
        patch(app, a_id, json!({"notes": null, "tags": null})).await.json().await.unwrap();
    assert!(cleared["notes"].is_null() && cleared["tags"] == json!([]));
    assert_eq!(cleared["name"], "renamed");

    // Bad labels: exact status and code, and nothing changed or stored.
    let before = app.count_rows("jobs").await;
    let bad_bodies = [
        json!({"name": "x".repeat(201)}),
        json!({"tags": ["has space"]}),
        json!({"tags": (0..33).map(|i| format!("t{i}")).collect::<Vec<_>>()}),
        json!({"notes": "bell\u{7}"}),
    ];
    for bad in &bad_bodies {
        let mut body = json!({"algorithm": "bc", "unlabeled_dataset": u});
        body.as_object_mut().unwrap().extend(bad.as_object().unwrap().clone());
        let created = app.post("/v1/jobs").json(&body).send().await.unwrap();
        assert_error(created, StatusCode::UNPROCESSABLE_ENTITY, "invalid_labels").await;
        let patched = patch(app, b_id, bad.clone()).await;
        assert_error(patched, StatusCode::UNPROCESSABLE_ENTITY, "invalid_labels").await;
    }
    let typed = patch(app, b_id, json!({"tags": "not-a-list"})).await;
    assert_error(typed, StatusCode::UNPROCESSABLE_ENTITY, "invalid_body").await;
    let unknown = patch(app, b_id, json!({"status": "succeeded"})).await;
    assert_error(unknown, StatusCode::UNPROCESSABLE_ENTITY, "invalid_body").await;
    assert_error(patch(app, "nope", json!({})).await, StatusCode::NOT_FOUND, "not_found").await;
    let bad_tag = app.get("/v1/jobs?tag=a%20b").send().await.unwrap();
    assert_error(bad_tag, StatusCode::BAD_REQUEST, "invalid_filter").await;
    assert_eq!(app.count_rows("jobs").await, before);
    let b_now = get_json(&app.client, &app.url(&format!("/v1/jobs/{b_id}"))).await;
    assert_eq!((&b_now["name"], &b_now["tags"]), (&json!("under_score"), &json!(["env=grid"])));
}

/// Reads a job's log as server-sent events until the stream ends.
async fn follow_log(app: &TestApp, id: &str) -> Vec<Value> {
    let response = app.get(&format!("/v1/jobs/{id}/logs?follow=true")).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let mut text = String::new();
    let mut body = response.bytes_stream();
    let read = async {
        while let Some(chunk) = body.next().await {
            text.push_str(&String::from_utf8_lossy(&chunk.unwrap()));
        }
    };
    tokio::time::timeout(Duration::from_secs(120), read).await.expect("the stream ends");
    text.lines()
        .filter_map(|l| l.strip_prefix("data:"))
        .map(|d| serde_json::from_str(d.trim()).unwrap())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_logs_its_story_and_exports_its_metrics() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_six_rooms(&app.client, &app.base_url).await;
    let job = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": small_config(200, 0),
               "runner": {"log_every": 10, "checkpoint_every": 100},
               "eval": {"env": "six-rooms", "episodes": 4, "every": 100}}),
    )
    .await;
    let id = job["id"].as_str().unwrap();
    // Followed from the start: the stream ends once the job has finished.
    let followed = follow_log(&app, id).await;
    let as_events: Vec<(String, Value)> =
        followed.iter().map(|l| ("log".into(), l.clone())).collect();
    crate::openapi::assert_events_declared(&app, "/v1/jobs/{id}/logs", &as_events).await;
    let job = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}"))).await;
    assert_eq!(job["status"], "succeeded");
    let lines: Vec<Value> = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}/logs")))
        .await
        .as_array()
        .unwrap()
        .clone();
    assert_eq!(followed, lines, "following gives the same lines");
    let messages: Vec<&str> = lines.iter().map(|l| l["message"].as_str().unwrap()).collect();
    let seqs: Vec<u64> = lines.iter().map(|l| l["seq"].as_u64().unwrap()).collect();
    assert_eq!(seqs, (1..=lines.len() as u64).collect::<Vec<_>>(), "{messages:?}");
    let worker = job["worker"].as_str().unwrap();
    // Info lines, but for the warning of SafeDICE's uniform fallback where this job's short
    // discriminator phase cannot tell D^N from D^U on held-out rows.
    let expected_level = |l: &Value| {
        let fallback = l["message"].as_str().unwrap().starts_with("weighting: uniform, ");
        l["level"] == if fallback { "warn" } else { "info" }
    };
    assert!(lines.iter().all(|l| l["worker"] == worker && expected_level(l)), "{lines:?}");
    let has = |prefix: &str| messages.iter().any(|m| m.starts_with(prefix));
    assert_eq!(messages[0], format!("claimed by worker {worker} (attempt 1 of 3)"));
    assert!(has("training from scratch: "), "{messages:?}");
    assert!(
        has("phase discriminator from step 0") && has("phase policy from step"),
        "{messages:?}"
    );
    let alpha = format!("alpha-hat (Eq. 15) = {:.4}", job["alpha_hat"].as_f64().unwrap());
    // The value, then how it was estimated (Best Bin Estimation on held-out episodes).
    let alpha_line = messages.iter().find(|m| m.starts_with(&alpha)).expect("alpha-hat logged");
    assert!(alpha_line.contains("held-out AUC"), "{alpha_line}");
    assert!(has("evaluation at step ") && has("checkpoint at step "), "{messages:?}");
    let policy = job["policy_id"].as_str().unwrap();
    assert!(messages.last().unwrap().ends_with(&format!(": policy {policy}")), "{messages:?}");
    let tail =
        get_json(&app.client, &app.url(&format!("/v1/jobs/{id}/logs?after=2&limit=1"))).await;
    assert_eq!(tail.as_array().unwrap(), &lines[2..3]);

    // Metric names, and the CSV holds every point the JSON history holds.
    let names = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}/metrics/names"))).await;
    let names = names.as_array().unwrap();
    let loss = names.iter().find(|m| m["name"] == "policy_loss").expect("policy_loss");
    assert!(names.iter().any(|m| m["name"] == "eval/normalized_return"), "{names:?}");
    let history = get_json(
        &app.client,
        &app.url(&format!("/v1/jobs/{id}/metrics?names=policy_loss&max_points=10000")),
    )
    .await;
    let rows = history["rows"].as_array().unwrap();
    assert_eq!(loss["points"].as_u64(), Some(rows.len() as u64));
    assert_eq!(loss["last_step"], rows.last().unwrap()["step"]);
    let csv =
        app.get(&format!("/v1/jobs/{id}/metrics.csv?names=policy_loss")).send().await.unwrap();
    assert_eq!(csv.status(), StatusCode::OK);
    assert!(csv.headers()["content-type"].to_str().unwrap().starts_with("text/csv"));
    let disposition = csv.headers()["content-disposition"].to_str().unwrap().to_owned();
    assert_eq!(disposition, format!("attachment; filename=\"job-{id}-metrics.csv\""));
    let csv = csv.text().await.unwrap();
    let mut csv_lines = csv.lines();
    assert_eq!(csv_lines.next(), Some("name,step,value,time"));
    let parsed: Vec<(u64, f64)> = csv_lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[1].parse().unwrap(), f[2].parse().unwrap())
        })
        .collect();
    let want: Vec<(u64, f64)> =
        rows.iter().map(|r| (r["step"].as_u64().unwrap(), r["value"].as_f64().unwrap())).collect();
    // serde_json's default float parsing may be one ulp off; the CSV's values are exact.
    assert_eq!(parsed.len(), want.len());
    for ((step, value), (want_step, want_value)) in parsed.iter().zip(&want) {
        assert_eq!(step, want_step);
        assert!((value - want_value).abs() <= 1e-12 * want_value.abs().max(1.0), "{value}");
    }

    for (path, status, code) in [
        ("/v1/jobs/nope/logs", StatusCode::NOT_FOUND, "not_found"),
        ("/v1/jobs/nope/metrics/names", StatusCode::NOT_FOUND, "not_found"),
        ("/v1/jobs/nope/metrics.csv", StatusCode::NOT_FOUND, "not_found"),
    ] {
        assert_error(app.get(path).send().await.unwrap(), status, code).await;
    }
    let bad_limit = app.get(&format!("/v1/jobs/{id}/logs?limit=0")).send().await.unwrap();
    assert_error(bad_limit, StatusCode::BAD_REQUEST, "invalid_limit").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deletes_follow_their_rules_and_remove_everything_they_say() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_six_rooms(&app.client, &app.base_url).await;
    let endless = json!({"algorithm": "bc", "unlabeled_dataset": u,
                         "config": small_config(ENDLESS_ITERATIONS, 0)});
    let running = create_job(&app.client, &app.base_url, endless).await;
    let running_id = running["id"].as_str().unwrap();
    wait_for_status(&app.client, &app.base_url, running_id, "running").await;
    let refused = app.delete(&format!("/v1/jobs/{running_id}")).send().await.unwrap();
    let message = assert_error(refused, StatusCode::CONFLICT, "job_active").await;
    assert!(message.contains("is running") && message.contains("/cancel"), "{message}");
    let used = app.delete(&format!("/v1/datasets/{u}")).send().await.unwrap();
    assert_error(used, StatusCode::CONFLICT, "dataset_in_use").await;
    app.post(&format!("/v1/jobs/{running_id}/cancel")).send().await.unwrap();
    wait_for_status(&app.client, &app.base_url, running_id, "cancelled").await;

    let done = bc_job(&app, &u, json!({})).await;
    let done_id = done["id"].as_str().unwrap();
    let done = wait_for_status(&app.client, &app.base_url, done_id, "succeeded").await;
    let policy = done["policy_id"].as_str().unwrap().to_owned();
    let act = json!({"observations": [vec![0.0; 103]]});
    let acted = app.post(&format!("/v1/policies/{policy}/act")).json(&act).send().await.unwrap();
    assert_eq!(acted.status(), StatusCode::OK, "the policy serves before the delete");
    let n_used = app.delete(&format!("/v1/datasets/{n}")).send().await.unwrap();
    assert_eq!(n_used.status(), StatusCode::NO_CONTENT, "no queued or running job uses it");
    let evaluation: Value = app
        .post(&format!("/v1/policies/{policy}/evaluate"))
        .json(&json!({"env": "six-rooms", "episodes": 2}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let evaluation_id = evaluation["id"].as_str().unwrap().to_owned();
    let location = format!("/v1/evaluations/{evaluation_id}");
    wait_for_evaluation(&app.client, &app.base_url, &location).await;

    // An evaluation alone; then the job with its policy and the rest of its records.
    let deleted = app.delete(&format!("/v1/evaluations/{evaluation_id}")).send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);
    let gone = app.get(&format!("/v1/evaluations/{evaluation_id}")).send().await.unwrap();
    assert_error(gone, StatusCode::NOT_FOUND, "not_found").await;
    let deleted = app.delete(&format!("/v1/jobs/{done_id}")).send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);
    for path in [
        format!("/v1/jobs/{done_id}"),
        format!("/v1/jobs/{done_id}/logs"),
        format!("/v1/policies/{policy}"),
    ] {
        assert_error(app.get(&path).send().await.unwrap(), StatusCode::NOT_FOUND, "not_found")
            .await;
    }
    let acted = app.post(&format!("/v1/policies/{policy}/act")).json(&act).send().await.unwrap();
    assert_error(acted, StatusCode::NOT_FOUND, "not_found").await;
    let again = app.delete(&format!("/v1/jobs/{done_id}")).send().await.unwrap();
    assert_error(again, StatusCode::NOT_FOUND, "not_found").await;
    for table in ["policies", "evaluations"] {
        assert_eq!(app.count_rows(table).await, 0, "{table}");
    }
    // The cancelled job's records are all that is left; then it goes too, and the dataset.
    let kept = app.count_rows("job_metrics").await;
    let deleted = app.delete(&format!("/v1/jobs/{running_id}")).send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);
    for table in ["jobs", "job_metrics", "job_checkpoints", "job_logs"] {
        assert_eq!(app.count_rows(table).await, 0, "{table} (had {kept} metric rows)");
    }
    let deleted = app.delete(&format!("/v1/datasets/{u}")).send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_is_deleted_alone_and_its_job_stays() {
    let app = TestApp::spawn().await;
    let (unlabeled, _) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let job = bc_job(&app, &u, json!({"name": "keep me"})).await;
    let id = job["id"].as_str().unwrap();
    let job = wait_for_status(&app.client, &app.base_url, id, "succeeded").await;
    let policy = job["policy_id"].as_str().unwrap();
    let deleted = app.delete(&format!("/v1/policies/{policy}")).send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);
    let job = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}"))).await;
    assert_eq!(
        (job["status"].as_str(), job["name"].as_str()),
        (Some("succeeded"), Some("keep me"))
    );
    assert!(job["policy_id"].is_null());
    let again = app.delete(&format!("/v1/policies/{policy}")).send().await.unwrap();
    assert_error(again, StatusCode::NOT_FOUND, "not_found").await;
    let missing = app.delete("/v1/evaluations/nope").send().await.unwrap();
    assert_error(missing, StatusCode::NOT_FOUND, "not_found").await;
}

/// A policy deleted while its first `/act` is loading it stays deleted: the load that the delete
/// overtook must not put it in the serving cache, where `/act` and `/v2` would answer from it
/// until a restart while `GET /v1/policies/{id}` says 404. Raced many times over, each delete
/// landing at another moment of the load (wide networks, so that a load takes milliseconds);
/// after each race every route answers 404 for the deleted policy.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_policy_deleted_while_its_first_act_loads_it_is_never_served_again() {
    const RACES: usize = 32;
    let app = TestApp::spawn_with(|c| c.workers = 2).await;
    let (unlabeled, _) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    // One policy to time a first load with, and one per race; a single step is enough to have
    // a policy, and the width is what makes it slow to load.
    let mut jobs = Vec::new();
    for seed in 0..=RACES as u64 {
        let body = json!({"algorithm": "bc", "unlabeled_dataset": u,
                          "config": {"iterations": 1, "seed": seed, "hidden_sizes": [1024, 1024],
                                     "batch_size": 64}});
        jobs.push(create_job(&app.client, &app.base_url, body).await);
    }
    let mut policies = Vec::new();
    for job in &jobs {
        let id = job["id"].as_str().unwrap();
        let job = wait_for_status(&app.client, &app.base_url, id, "succeeded").await;
        policies.push(job["policy_id"].as_str().unwrap().to_owned());
    }
    let act_body = json!({"observations": grid_observations()});
    let flat: Vec<f32> = grid_observations().into_iter().flatten().collect();
    let infer_body = json!({"inputs": [{"name": "observations", "datatype": "FP32",
                                        "shape": [GRID_OBS_DIM, GRID_OBS_DIM], "data": flat}]});
    let act = |policy: &str| app.post(&format!("/v1/policies/{policy}/act")).json(&act_body);

    let timed = policies.pop().unwrap();
    let started = std::time::Instant::now();
    assert_eq!(act(&timed).send().await.unwrap().status(), StatusCode::OK);
    let first_load = started.elapsed();
    let started = std::time::Instant::now();
    assert_eq!(act(&timed).send().await.unwrap().status(), StatusCode::OK);
    let loaded = started.elapsed();

    let mut answers = std::collections::BTreeMap::new();
    for (race, policy) in policies.iter().enumerate() {
        // From at once to past the end of a first load, spread evenly over the races.
        let delay = first_load.mul_f64(1.5 * race as f64 / RACES as f64);
        let (raced, deleted) = tokio::join!(act(policy).send(), async {
            tokio::time::sleep(delay).await;
            app.delete(&format!("/v1/policies/{policy}")).send().await
        });
        assert_eq!(deleted.unwrap().status(), StatusCode::NO_CONTENT, "race {race}");
        // The act that raced the delete answers from the policy (it read it before the delete)
        // or not at all; never an error of another kind.
        let raced = raced.unwrap().status();
        assert!(matches!(raced, StatusCode::OK | StatusCode::NOT_FOUND), "race {race}: {raced}");
        *answers.entry(raced.as_u16()).or_insert(0) += 1;

        let again = act(policy).send().await.unwrap();
        assert_eq!(again.status(), StatusCode::NOT_FOUND, "race {race}: served after its delete");
        assert_error(again, StatusCode::NOT_FOUND, "not_found").await;
        let infer =
            app.post(&format!("/v2/models/{policy}/infer")).json(&infer_body).send().await.unwrap();
        assert_v2_error(infer, StatusCode::NOT_FOUND).await;
        let ready = app.get(&format!("/v2/models/{policy}/ready")).send().await.unwrap();
        assert_v2_error(ready, StatusCode::NOT_FOUND).await;
        let record = app.get(&format!("/v1/policies/{policy}")).send().await.unwrap();
        assert_error(record, StatusCode::NOT_FOUND, "not_found").await;
    }
    // What the races were like (a first load against a loaded policy's answer), for the log.
    eprintln!(
        "{RACES} races: first /act {first_load:?}, loaded /act {loaded:?}; racing /act \
         answered {answers:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn page_tokens_do_not_shift_when_jobs_are_added() {
    let app = TestApp::spawn_with(|c| c.workers = 0).await;
    let (unlabeled, _) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let mut first = Vec::new();
    for _ in 0..5 {
        first.push(bc_job(&app, &u, json!({})).await["id"].as_str().unwrap().to_owned());
    }
    let page = |query: String| {
        let url = app.url(&format!("/v1/jobs?limit=2{query}"));
        let client = app.client.clone();
        async move { get_json(&client, &url).await }
    };
    let mut seen = Vec::new();
    let mut token: Option<String> = None;
    loop {
        let query = token.as_ref().map_or(String::new(), |t| format!("&page_token={t}"));
        let body = page(query).await;
        seen.extend(ids_in_order(&body));
        // New jobs arrive between pages: with offsets every page would shift by two.
        bc_job(&app, &u, json!({})).await;
        bc_job(&app, &u, json!({})).await;
        match body["next_page_token"].as_str() {
            Some(next) => token = Some(next.to_owned()),
            None => break,
        }
        assert!(body["next_offset"].is_null() || token.is_some());
    }
    let mut want = first.clone();
    want.sort_by(|a, b| b.cmp(a));
    let mut got = seen.clone();
    got.sort_by(|a, b| b.cmp(a));
    assert_eq!(got, want, "every first job once, none added later: {seen:?}");

    // An offset with a token counts from the token's item (`seen` is in list order).
    let skipped = page(format!("&offset=1&page_token={}&tag=none", seen[0])).await;
    assert_eq!(skipped["total"], 0, "filters still apply");
    let skipped = page(format!("&offset=1&page_token={}", seen[0])).await;
    assert_eq!(ids_in_order(&skipped), seen[2..4]);
    let unknown = app.get("/v1/jobs?page_token=nope").send().await.unwrap();
    assert_error(unknown, StatusCode::NOT_FOUND, "page_token_not_found").await;
    for list in ["datasets", "policies", "evaluations"] {
        let unknown = app.get(&format!("/v1/{list}?page_token=nope")).send().await.unwrap();
        assert_error(unknown, StatusCode::NOT_FOUND, "page_token_not_found").await;
    }
    let datasets = get_json(&app.client, &app.url("/v1/datasets?limit=2")).await;
    assert_eq!(datasets["next_page_token"], Value::Null, "one dataset: a page that is not full");
}

fn ids_in_order(page: &Value) -> Vec<String> {
    page["items"].as_array().unwrap().iter().map(|j| j["id"].as_str().unwrap().into()).collect()
}

/// `--policy-cache-bytes` bounds what serving keeps loaded: with room for one policy, acting on
/// three in turn keeps one loaded (the others are dropped and loaded again when asked for), and
/// every answer is the one the policy gave first.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_policy_cache_keeps_to_its_byte_budget_and_answers_the_same() {
    let app = TestApp::spawn_with(|c| c.policy_cache_bytes = 1).await;
    let (u, _) = upload_six_rooms(&app.client, &app.base_url).await;
    let mut policies = Vec::new();
    for seed in 0..3 {
        let job = bc_job(&app, &u, json!({"config": small_config(60, seed)})).await;
        let done =
            wait_for_status(&app.client, &app.base_url, job["id"].as_str().unwrap(), "succeeded");
        policies.push(done.await["policy_id"].as_str().unwrap().to_owned());
    }
    let act = json!({"observations": [vec![0.0; 103], vec![1.0; 103]], "deterministic": false, "seed": 4});
    let answer = |policy: String| {
        let request = app.post(&format!("/v1/policies/{policy}/act")).json(&act).send();
        async move {
            let response = request.await.unwrap();
            assert_eq!(response.status(), StatusCode::OK);
            response.json::<Value>().await.unwrap()["actions"].clone()
        }
    };
    let mut first = Vec::new();
    for policy in &policies {
        first.push(answer(policy.clone()).await);
    }
    for round in 0..2 {
        for (policy, expected) in policies.iter().zip(&first) {
            assert_eq!(&answer(policy.clone()).await, expected, "round {round}");
        }
    }
    let metrics = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    assert!(metrics.lines().any(|l| l == "safedice_policies_loaded 1"), "{metrics}");
}
