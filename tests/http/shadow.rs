//! Shadow versions through the real server: an alias's shadow acts on its share of the requests
//! beside the version that answers, never answers itself, and its comparison series says how far
//! it is from production: exactly the disagreements of the two policies on a known set of
//! observations (discrete), zero for a copy of production even when actions are sampled (the two
//! draw the same noise), the L2 distance of the deterministic actions (continuous). A shadow that
//! takes other observations, or a share out of range, is refused with nothing stored; a version in
//! use as a shadow cannot be deleted; promoting the shadow under load fails no request.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::support::app::{assert_error, TestApp};
use crate::support::jobs::*;
use crate::support::tasks;
use reqwest::StatusCode;
use serde_json::{json, Value};

/// Policies of BC jobs on `dataset` with the given seeds.
async fn policies(app: &TestApp, dataset: &str, seeds: &[u64]) -> Vec<String> {
    let mut trained = Vec::new();
    for &seed in seeds {
        let body = json!({"algorithm": "bc", "unlabeled_dataset": dataset,
                          "config": small_config(60, seed)});
        let job = create_job(&app.client, &app.base_url, body).await;
        let done =
            wait_for_status(&app.client, &app.base_url, job["id"].as_str().unwrap(), "succeeded")
                .await;
        trained.push(done["policy_id"].as_str().unwrap().to_owned());
    }
    trained
}

/// Model `name` with one version per policy, in order.
async fn model_of(app: &TestApp, name: &str, policies: &[&str]) {
    let created = app.post("/v1/models").json(&json!({"name": name})).send().await.unwrap();
    assert_eq!(created.status(), StatusCode::CREATED);
    for policy in policies {
        let response = app
            .post(&format!("/v1/models/{name}/versions"))
            .json(&json!({"policy_id": policy}))
            .send()
            .await
            .unwrap();
        assert_eq!(response.status(), StatusCode::CREATED);
    }
}

async fn put_alias(app: &TestApp, model: &str, alias: &str, body: &Value) -> reqwest::Response {
    let path = format!("/v1/models/{model}/aliases/{alias}");
    app.request(reqwest::Method::PUT, &path).json(body).send().await.unwrap()
}

async fn ok_json(response: reqwest::Response) -> Value {
    let status = response.status();
    let body: Value = response.json().await.unwrap();
    assert_eq!(status, StatusCode::OK, "{body}");
    body
}

/// `/act` on `path`: (the actions, the answering version).
async fn act(app: &TestApp, path: &str, body: &Value) -> (Value, String) {
    let response = app.post(path).json(body).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK, "{path}");
    let version = response.headers()["x-safedice-model-version"].to_str().unwrap().to_owned();
    let body: Value = response.json().await.unwrap();
    (body["actions"].clone(), version)
}

async fn series(app: &TestApp, model: &str) -> Vec<Value> {
    let report = get_json(&app.client, &app.url(&format!("/v1/models/{model}/shadow"))).await;
    report["series"].as_array().unwrap().clone()
}

fn the_series(all: &[Value], production: u64, shadow: u64) -> &Value {
    all.iter()
        .find(|s| {
            s["production_version"].as_u64() == Some(production)
                && s["shadow_version"].as_u64() == Some(shadow)
        })
        .unwrap_or_else(|| panic!("no series {production} vs {shadow} in {all:?}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_discrete_shadow_counts_exactly_the_disagreements_and_never_answers() {
    let app = TestApp::spawn_with(|c| c.workers = 2).await;
    let (unlabeled, _) = grid_datasets();
    let dataset = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let trained = policies(&app, &dataset, &[1, 2]).await;
    // v1 and v3 are the same policy: a shadow of v1 by v3 never disagrees.
    model_of(&app, "pilot", &[&trained[0], &trained[1], &trained[0]]).await;
    let observations = json!({"observations": grid_observations()});
    let rows = grid_observations().len() as u64;
    let (first, _) = act(&app, "/v1/models/pilot/versions/1/act", &observations).await;
    let (second, _) = act(&app, "/v1/models/pilot/versions/2/act", &observations).await;
    let differing = first
        .as_array()
        .unwrap()
        .iter()
        .zip(second.as_array().unwrap())
        .filter(|(a, b)| a != b)
        .count() as u64;
    assert!(differing > 0, "the two seeds' policies agree everywhere: {first} {second}");

    let shadowed = json!({"version": 1, "shadow": {"version": 2, "sample": 1.0}});
    let moved = ok_json(put_alias(&app, "pilot", "production", &shadowed).await).await;
    assert_eq!(moved["shadow"], json!({"version": 2, "sample": 1.0}));
    let model = get_json(&app.client, &app.url("/v1/models/pilot")).await;
    assert_eq!(model["aliases"][0]["shadow"], json!({"version": 2, "sample": 1.0}));
    for _ in 0..20 {
        let (actions, version) = act(&app, "/v1/models/pilot@production/act", &observations).await;
        assert_eq!((&actions, version.as_str()), (&first, "1"), "the shadow answered");
    }
    // The Open Inference Protocol's route is shadowed too.
    let flat: Vec<f32> = grid_observations().concat();
    let infer = json!({"inputs": [{"name": "observations", "datatype": "FP32",
        "shape": [rows, GRID_OBS_DIM], "data": flat}]});
    let response = app.post("/v2/models/pilot@production/infer").json(&infer).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);

    let all = series(&app, "pilot").await;
    assert_eq!(all.len(), 1, "{all:?}");
    let compared = the_series(&all, 1, 2);
    let total = &compared["total"];
    assert_eq!(
        (compared["alias"].as_str(), compared["actions"].as_str()),
        (Some("production"), Some("discrete"))
    );
    assert_eq!(
        (total["requests"].as_u64(), total["skipped"].as_u64(), total["failed"].as_u64()),
        (Some(21), Some(0), Some(0)),
        "{total}"
    );
    assert_eq!(total["observations"].as_u64(), Some(21 * rows));
    let rate = total["disagreement_rate"].as_f64().unwrap();
    assert!((rate - differing as f64 / rows as f64).abs() < 1e-12, "{rate} vs {differing}/{rows}");
    assert!(total["mean_l2"].is_null() && total["shadow_mean_log_ratio"].is_null(), "{total}");
    let metrics = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    assert!(
        metrics.contains("safedice_shadow_requests_total{result=\"compared\"} 21\n")
            && metrics.contains("safedice_shadow_queue 0\n"),
        "{metrics}"
    );
    let points = compared["points"].as_array().unwrap();
    let summed: u64 = points.iter().map(|p| p["requests"].as_u64().unwrap()).sum();
    assert_eq!(summed, 21, "the minutes add up to the total: {points:?}");

    // A copy of production as the shadow, sampled actions without a seed: the two draw the
    // same noise, so they never disagree.
    let copy = json!({"version": 1, "shadow": {"version": 3, "sample": 1.0}});
    ok_json(put_alias(&app, "pilot", "production", &copy).await).await;
    let sampled = json!({"observations": grid_observations(), "deterministic": false});
    for _ in 0..10 {
        act(&app, "/v1/models/pilot@production/act", &sampled).await;
    }
    let all = series(&app, "pilot").await;
    let same = &the_series(&all, 1, 3)["total"];
    assert_eq!(
        (same["requests"].as_u64(), same["disagreement_rate"].as_f64()),
        (Some(10), Some(0.0))
    );

    // A quarter of the requests: drawn at random, about 100 of 400.
    let quarter = json!({"version": 1, "shadow": {"version": 2, "sample": 0.25}});
    ok_json(put_alias(&app, "pilot", "production", &quarter).await).await;
    let one = json!({"observations": [grid_observations()[0].clone()]});
    for _ in 0..400 {
        act(&app, "/v1/models/pilot@production/act", &one).await;
    }
    let all = series(&app, "pilot").await;
    let drawn = the_series(&all, 1, 2)["total"]["requests"].as_u64().unwrap() - 21;
    // Binomial(400, 0.25): mean 100, sd 8.7; [55, 145] holds with overwhelming probability.
    assert!((55..=145).contains(&drawn), "{drawn} of 400 requests shadowed at 25%");

    // A version in use as a shadow is not deleted; the history keeps the shadows.
    let deleted = app.delete("/v1/models/pilot/versions/2").send().await.unwrap();
    assert_error(deleted, StatusCode::CONFLICT, "version_in_use").await;
    let history = get_json(&app.client, &app.url("/v1/models/pilot/history")).await;
    let latest = &history["items"][0];
    assert_eq!(
        (&latest["from_shadow"], &latest["shadow"]),
        (&json!({"version": 3, "sample": 1.0}), &json!({"version": 2, "sample": 0.25}))
    );
    // A move without a shadow ends it.
    let ended = ok_json(put_alias(&app, "pilot", "production", &json!({"version": 1})).await).await;
    assert!(ended["shadow"].is_null(), "{ended}");

    // Counts not yet flushed when the model is deleted and created again under its name belong
    // to the deleted model: the new one's series starts empty.
    let name = "pilot-again";
    model_of(&app, name, &[&trained[0], &trained[1]]).await;
    ok_json(put_alias(&app, name, "production", &shadowed).await).await;
    for _ in 0..5 {
        act(&app, &format!("/v1/models/{name}@production/act"), &observations).await;
    }
    let gone = app.delete(&format!("/v1/models/{name}/aliases/production")).send().await.unwrap();
    assert_eq!(gone.status(), StatusCode::NO_CONTENT);
    let gone = app.delete(&format!("/v1/models/{name}")).send().await.unwrap();
    assert_eq!(gone.status(), StatusCode::NO_CONTENT);
    model_of(&app, name, &[&trained[0], &trained[1]]).await;
    ok_json(put_alias(&app, name, "production", &shadowed).await).await;
    assert_eq!(series(&app, name).await, Vec::<Value>::new(), "the deleted model's counts");
    act(&app, &format!("/v1/models/{name}@production/act"), &observations).await;
    let all = series(&app, name).await;
    assert_eq!(the_series(&all, 1, 2)["total"]["requests"].as_u64(), Some(1), "{all:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_continuous_shadow_reports_the_l2_distance_and_bad_shadows_are_refused() {
    let app = TestApp::spawn_with(|c| c.workers = 2).await;
    let point = upload(&app.client, &app.base_url, &tasks::point_dataset(6, 6, 5), "point").await;
    let (grid, _) = grid_datasets();
    let grid = upload(&app.client, &app.base_url, &grid, "grid").await;
    let trained = policies(&app, &point, &[1, 2]).await;
    let other = policies(&app, &grid, &[1]).await;
    model_of(&app, "walker", &[&trained[0], &trained[1], &other[0]]).await;
    let observations: Vec<[f32; 2]> = (0..8).map(|i| [i as f32 * 0.1, 0.05 * i as f32]).collect();
    let body = json!({"observations": observations});
    let (first, _) = act(&app, "/v1/models/walker/versions/1/act", &body).await;
    let (second, _) = act(&app, "/v1/models/walker/versions/2/act", &body).await;
    let distances: Vec<f64> = first
        .as_array()
        .unwrap()
        .iter()
        .zip(second.as_array().unwrap())
        .map(|(a, b)| {
            let (a, b) = (a.as_array().unwrap(), b.as_array().unwrap());
            let squares: f64 = a
                .iter()
                .zip(b)
                .map(|(x, y)| (x.as_f64().unwrap() - y.as_f64().unwrap()).powi(2))
                .sum();
            squares.sqrt()
        })
        .collect();
    let mean = distances.iter().sum::<f64>() / distances.len() as f64;
    let largest = distances.iter().cloned().fold(0.0, f64::max);
    assert!(mean > 0.0, "the two seeds' policies act alike");

    // Refused, nothing stored: a shadow that takes the grid's observations, and shares out of
    // range.
    let before = get_json(&app.client, &app.url("/v1/models/walker/history")).await;
    let mismatched = json!({"version": 1, "shadow": {"version": 3, "sample": 0.5}});
    let message = assert_error(
        put_alias(&app, "walker", "production", &mismatched).await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_shadow",
    )
    .await;
    assert!(message.contains("version 1 takes 2 and gives 2-dimensional actions"), "{message}");
    // Checked against the canary too: whichever answers is compared with the shadow.
    let beside_canary = json!({"version": 1, "canary": {"version": 3, "weight": 0.5},
                               "shadow": {"version": 2, "sample": 0.5}});
    let message = assert_error(
        put_alias(&app, "walker", "production", &beside_canary).await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_shadow",
    )
    .await;
    assert!(message.contains("version 3 takes 10"), "{message}");
    for sample in [0.0, 1.5, -0.1] {
        let bad = json!({"version": 1, "shadow": {"version": 2, "sample": sample}});
        let response = put_alias(&app, "walker", "production", &bad).await;
        assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_shadow").await;
    }
    let after = get_json(&app.client, &app.url("/v1/models/walker/history")).await;
    assert_eq!(before, after, "a refused shadow moved the alias");
    let window = app.get("/v1/models/walker/shadow?minutes=0").send().await.unwrap();
    assert_error(window, StatusCode::BAD_REQUEST, "invalid_window").await;

    let shadowed = json!({"version": 1, "shadow": {"version": 2, "sample": 1.0}});
    ok_json(put_alias(&app, "walker", "production", &shadowed).await).await;
    for _ in 0..5 {
        act(&app, "/v1/models/walker@production/act", &body).await;
    }
    let all = series(&app, "walker").await;
    let compared = the_series(&all, 1, 2);
    let total = &compared["total"];
    assert_eq!(
        (compared["actions"].as_str(), total["observations"].as_u64()),
        (Some("continuous"), Some(40))
    );
    let (mean_l2, max_l2) = (total["mean_l2"].as_f64().unwrap(), total["max_l2"].as_f64().unwrap());
    // The server compares f32 actions; the JSON carries them to the test exactly.
    assert!(
        (mean_l2 - mean).abs() < 1e-5 && (max_l2 - largest).abs() < 1e-5,
        "{total}: {mean} {largest}"
    );
    assert!(total["max_max_abs"].as_f64().unwrap() <= max_l2 + 1e-9);
    assert!(
        total["disagreement_rate"].is_null() && total["mean_shadow_ms"].as_f64().unwrap() > 0.0
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn promoting_the_shadow_under_load_fails_no_request() {
    let app = TestApp::spawn_with(|c| c.workers = 2).await;
    let (unlabeled, _) = grid_datasets();
    let dataset = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let trained = policies(&app, &dataset, &[1, 2]).await;
    model_of(&app, "pilot", &[&trained[0], &trained[1]]).await;
    let shadowed = json!({"version": 1, "shadow": {"version": 2, "sample": 1.0}});
    ok_json(put_alias(&app, "pilot", "production", &shadowed).await).await;

    let (answered, failed) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
    let promoted_at = Instant::now() + Duration::from_millis(600);
    let agents: Vec<_> = (0..4)
        .map(|_| {
            let (client, url) = (app.client.clone(), app.url("/v1/models/pilot@production/act"));
            let (answered, failed) = (answered.clone(), failed.clone());
            tokio::spawn(async move {
                let mut versions = Vec::new();
                while Instant::now() < promoted_at + Duration::from_millis(600) {
                    let body = json!({"observations": grid_observations()});
                    match client.post(&url).json(&body).send().await {
                        Ok(r) if r.status() == StatusCode::OK => {
                            versions.push(
                                r.headers()["x-safedice-model-version"]
                                    .to_str()
                                    .unwrap()
                                    .to_owned(),
                            );
                            answered.fetch_add(1, Ordering::Relaxed);
                        }
                        _ => {
                            failed.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
                versions
            })
        })
        .collect();
    tokio::time::sleep_until(promoted_at.into()).await;
    // The page's Promote: the shadow's version, only if the alias is still where it was seen.
    let promote = json!({"version": 2, "expected_version": 1, "reason": "promoted from shadow"});
    let moved = ok_json(put_alias(&app, "pilot", "production", &promote).await).await;
    assert_eq!(
        (moved["from_shadow"]["version"].as_u64(), moved["shadow"].is_null()),
        (Some(2), true)
    );
    let mut last_versions = Vec::new();
    for agent in agents {
        last_versions.push(agent.await.unwrap().last().cloned());
    }
    assert_eq!(failed.load(Ordering::Relaxed), 0, "requests failed across the promotion");
    assert!(answered.load(Ordering::Relaxed) > 8, "too few requests to say anything");
    assert!(last_versions.iter().all(|v| v.as_deref() == Some("2")), "{last_versions:?}");
    let (_, version) =
        act(&app, "/v1/models/pilot@production/act", &json!({"observations": grid_observations()}))
            .await;
    assert_eq!(version, "2");
}
