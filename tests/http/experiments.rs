//! Experiments through the real server: a grid of algorithms × seeds queued as jobs, its
//! results equal to a hand computation from the per-seed values (mean, standard error), later
//! evaluations of one seed kept under their own protocols without moving the means, CSV, cancel
//! and delete of the whole grid, and bad requests refused with the field named and nothing
//! stored.

use std::time::{Duration, Instant};

use crate::support::app::{assert_error, TestApp};
use crate::support::jobs::*;
use reqwest::StatusCode;
use serde_json::{json, Value};

fn grid(unlabeled: &str, non_preferred: &str, seeds: Value) -> Value {
    json!({
        "name": "rooms", "unlabeled_dataset": unlabeled, "non_preferred_dataset": non_preferred,
        "algorithms": ["bc", {"algorithm": "safedice", "label": "safedice-small",
                              "config": {"discriminator_iterations": 20}}],
        "seeds": seeds,
        "config": {"iterations": 60, "hidden_sizes": [16, 16], "batch_size": 32},
        "eval": {"env": "six-rooms", "every": 30, "episodes": 8, "seed": 1},
        "tags": ["grid-test"],
    })
}

async fn wait_for_grid(app: &TestApp, id: &str) -> Value {
    let started = Instant::now();
    loop {
        let experiment = get_json(&app.client, &app.url(&format!("/v1/experiments/{id}"))).await;
        let progress = &experiment["progress"];
        if progress["succeeded"] == progress["total"] {
            return experiment;
        }
        assert_eq!(progress["failed"], 0, "{experiment}");
        assert!(started.elapsed() < Duration::from_secs(300), "grid stuck: {progress}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn mean_and_se(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let variance = values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (n - 1.0);
    (mean, (variance / n).sqrt())
}

#[tokio::test]
async fn a_grid_runs_as_jobs_and_reports_mean_and_standard_error_per_algorithm() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_six_rooms(&app.client, &app.base_url).await;
    let response =
        app.post("/v1/experiments").json(&grid(&u, &n, json!([5, 3, 10]))).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::CREATED);
    let created: Value = response.json().await.unwrap();
    let id = created["id"].as_str().unwrap().to_owned();
    assert_eq!(created["progress"]["total"], 6);

    // The grid is six ordinary jobs, named and tagged, BC without Dᴺ.
    let jobs = get_json(&app.client, &app.url(&format!("/v1/jobs?tag=experiment={id}"))).await;
    assert_eq!(jobs["total"], 6);
    for job in jobs["items"].as_array().unwrap() {
        assert_eq!(job["experiment_id"], id.as_str());
        assert!(job["tags"].as_array().unwrap().contains(&json!("grid-test")));
        let name = job["name"].as_str().unwrap();
        assert!(name.starts_with("rooms · "), "{name}");
        if job["algorithm"] == "bc" {
            assert_eq!(job["non_preferred_dataset"], Value::Null);
        }
    }

    let done = wait_for_grid(&app, &id).await;
    let results = done["results"].as_array().unwrap();
    assert_eq!(
        results.iter().map(|r| r["label"].clone()).collect::<Vec<_>>(),
        [json!("bc"), json!("safedice-small")]
    );
    for arm in results {
        let label = arm["label"].as_str().unwrap();
        let per_seed: Vec<&Value> =
            done["jobs"].as_array().unwrap().iter().filter(|j| j["arm"] == label).collect();
        assert_eq!(
            per_seed.iter().map(|j| j["seed"].as_u64().unwrap()).collect::<Vec<_>>(),
            [5, 3, 10]
        );
        for metric in ["normalized_return", "average_cost", "cost_violation_ratio", "cvar_cost_10"]
        {
            let values: Vec<f64> =
                per_seed.iter().map(|j| j["metrics"][metric].as_f64().unwrap()).collect();
            let (mean, se) = mean_and_se(&values);
            let summary = &arm["metrics"][metric];
            assert_eq!(summary["n"], 3);
            assert_eq!(summary["values"], json!(values));
            assert!(
                (summary["mean"].as_f64().unwrap() - mean).abs() <= 1e-9 * mean.abs().max(1.0),
                "{metric}"
            );
            assert!((summary["se"].as_f64().unwrap() - se).abs() <= 1e-9 * se.max(1.0), "{metric}");
        }
        // Each job's evaluation at the end of training, stored as an evaluation of its policy.
        assert!(
            per_seed.iter().all(|j| j["metrics_from"]
                .as_str()
                .is_some_and(|from| from.contains("(taken at training step ")
                    && from.ends_with(", six-rooms)"))),
            "{per_seed:?}"
        );
    }

    // One protocol so far: every job's evaluation at the end of training.
    let trained = "runtime=builtin;actions=sampled;episodes=8;seed=1;env=six-rooms";
    assert_eq!(
        (done["protocol"]["key"].as_str(), done["protocol_choice"].as_str()),
        (Some(trained), Some("shared_by_all"))
    );
    assert_eq!(done["protocols"].as_array().map(Vec::len), Some(1));
    assert_eq!(done["protocols"][0]["jobs"], 6);

    // Seed 5 of BC evaluated twice more, deterministically and in the user's own simulator: two
    // protocols beside the first, and the means over the seeds do not move.
    let first = &done["jobs"][0];
    let policy = first["policy_id"].as_str().unwrap();
    let queued = app
        .post(&format!("/v1/policies/{policy}/evaluate"))
        .json(&json!({"env": "six-rooms", "episodes": 8, "seed": 1, "deterministic": true}))
        .send()
        .await
        .unwrap();
    assert_eq!(queued.status(), StatusCode::ACCEPTED);
    let location = queued.headers()["location"].to_str().unwrap().to_owned();
    let deterministic = wait_for_evaluation(&app.client, &app.base_url, &location).await;
    let deterministic_key = "runtime=builtin;actions=deterministic;episodes=8;seed=1;env=six-rooms";
    assert_eq!(deterministic["protocol"]["key"], deterministic_key);
    let recorded = app
        .post(&format!("/v1/policies/{policy}/evaluations"))
        .json(&json!({"env": "my-sim", "returns": [1.0, 3.0], "costs": [0.0, 2.0],
                      "runtime": "onnx", "deterministic": true,
                      "reference": {"preferred_return": 4.0, "preferred_cost": 0.0,
                                    "non_preferred_return": 4.0, "non_preferred_cost": 4.0}}))
        .send()
        .await
        .unwrap();
    assert_eq!(recorded.status(), StatusCode::CREATED);
    let recorded: Value = recorded.json().await.unwrap();
    let external_key = "runtime=onnx;actions=deterministic;episodes=2;seed=0;env=my-sim";
    assert_eq!(
        (&recorded["runtime"], &recorded["protocol"]["key"]),
        (&json!("onnx"), &json!(external_key))
    );
    let again = get_json(&app.client, &app.url(&format!("/v1/experiments/{id}"))).await;
    assert_eq!(again["results"], done["results"], "a stray evaluation never moves a mean");
    assert_eq!(again["protocol"], done["protocol"]);
    let protocols: Vec<(&str, u64)> = again["protocols"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (p["protocol"]["key"].as_str().unwrap(), p["jobs"].as_u64().unwrap()))
        .collect();
    assert_eq!(protocols, [(trained, 6), (external_key, 1), (deterministic_key, 1)]);
    let job = &again["jobs"][0];
    assert_eq!(job["protocols"], json!([external_key, deterministic_key, trained]));
    assert_eq!(job["protocol"], trained);

    // Asked for, the recorded protocol: seed 5 of BC alone has numbers, and BC's mean is its.
    let url = app.url(&format!("/v1/experiments/{id}"));
    let response = app.client.get(&url).query(&[("protocol", external_key)]).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let external: Value = response.json().await.unwrap();
    assert_eq!(external["protocol_choice"], "requested");
    let job = &external["jobs"][0];
    assert!(job["metrics_from"].as_str().unwrap().contains("external, my-sim"), "{job}");
    assert_eq!(
        (job["metrics"]["normalized_return"].as_f64(), job["metrics"]["average_cost"].as_f64()),
        (Some(50.0), Some(1.0))
    );
    assert_eq!(external["jobs"][1]["metrics"], json!({}));
    assert_eq!(external["jobs"][1]["protocol"], Value::Null);
    let bc = &external["results"][0]["metrics"]["normalized_return"];
    assert_eq!((bc["n"].as_u64(), bc["mean"].as_f64()), (Some(1), Some(50.0)));
    assert_eq!(external["results"][1]["metrics"], json!({}));
    let unknown = app.client.get(&url).query(&[("protocol", "runtime=act")]).send().await.unwrap();
    let message = assert_error(unknown, StatusCode::NOT_FOUND, "not_found").await;
    assert!(message.contains(trained) && message.contains(external_key), "{message}");

    // The CSV: every protocol's values and aggregates, each labelled with its protocol.
    let csv = app.get(&format!("/v1/experiments/{id}/results.csv")).send().await.unwrap();
    assert_eq!(csv.headers()["content-type"], "text/csv");
    let csv = csv.text().await.unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("arm,algorithm,protocol,stat,seed,job_id,metric,value"));
    let mean_row = format!("safedice-small,safedice,{trained},mean,,,normalized_return,");
    let mean_row = lines.clone().find(|l| l.starts_with(&mean_row)).unwrap();
    let mean: f64 = mean_row.rsplit(',').next().unwrap().parse().unwrap();
    let arm = &again["results"][1]["metrics"]["normalized_return"]["mean"];
    assert_eq!(mean, arm.as_f64().unwrap());
    let values = |key: &str| {
        let prefix = format!(",{key},value,");
        lines.clone().filter(|l| l.contains(&prefix) && l.contains(",normalized_return,")).count()
    };
    assert_eq!((values(trained), values(deterministic_key), values(external_key)), (6, 1, 1));
    let n_row = format!("bc,bc,{external_key},n,,,normalized_return,1");
    assert!(lines.clone().any(|l| l == n_row), "{csv}");

    // Any jobs side by side by the same rule: the grid's first job twice and its second.
    let (a, b) = (first["job_id"].as_str().unwrap(), again["jobs"][1]["job_id"].as_str().unwrap());
    let side = get_json(&app.client, &app.url(&format!("/v1/results?jobs={a},{b},{a}"))).await;
    assert_eq!(side["protocol"]["key"], trained);
    let metrics: Vec<&Value> =
        side["jobs"].as_array().unwrap().iter().map(|j| &j["metrics"]).collect();
    assert_eq!(
        metrics,
        [&again["jobs"][0]["metrics"], &again["jobs"][1]["metrics"], &again["jobs"][0]["metrics"]]
    );
    let empty = app.get("/v1/results?jobs=,").send().await.unwrap();
    assert_error(empty, StatusCode::BAD_REQUEST, "invalid_jobs").await;
    let missing = app.get(&format!("/v1/results?jobs={a},no-such-job")).send().await.unwrap();
    assert_error(missing, StatusCode::NOT_FOUND, "not_found").await;

    let listed = get_json(&app.client, &app.url("/v1/experiments")).await;
    assert_eq!(
        (listed["total"].as_u64(), listed["items"][0]["id"].as_str()),
        (Some(1), Some(&*id))
    );
    assert_eq!(listed["items"][0]["progress"], again["progress"], "the list counts statuses too");
    assert_eq!(
        app.delete(&format!("/v1/experiments/{id}")).send().await.unwrap().status(),
        StatusCode::NO_CONTENT
    );
    assert_eq!(app.count_rows("jobs").await, 0, "the grid's jobs went with it");
    assert_eq!(app.count_rows("policies").await, 0);
}

#[tokio::test]
async fn a_grid_is_cancelled_and_deleted_as_a_whole() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_six_rooms(&app.client, &app.base_url).await;
    let mut body = grid(&u, &n, json!([0, 1]));
    body["config"]["iterations"] = ENDLESS_ITERATIONS.into();
    body["eval"] = Value::Null;
    let created: Value =
        app.post("/v1/experiments").json(&body).send().await.unwrap().json().await.unwrap();
    let id = created["id"].as_str().unwrap();
    let response = app.delete(&format!("/v1/experiments/{id}")).send().await.unwrap();
    assert_error(response, StatusCode::CONFLICT, "experiment_active").await;
    let cancelled: Value = app
        .post(&format!("/v1/experiments/{id}/cancel"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(cancelled["progress"]["queued"], 0, "{cancelled}");
    let started = Instant::now();
    loop {
        let grid = get_json(&app.client, &app.url(&format!("/v1/experiments/{id}"))).await;
        if grid["progress"]["cancelled"] == 4 {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "not all cancelled: {}",
            grid["progress"]
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(
        app.delete(&format!("/v1/experiments/{id}")).send().await.unwrap().status(),
        StatusCode::NO_CONTENT
    );
    assert_eq!((app.count_rows("jobs").await, app.count_rows("experiments").await), (0, 0));
    let response = app.get(&format!("/v1/experiments/{id}")).send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
}

#[tokio::test]
async fn a_bad_grid_is_refused_with_the_field_named_and_nothing_queued() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_six_rooms(&app.client, &app.base_url).await;
    let with = |change: &dyn Fn(&mut Value)| {
        let mut body = grid(&u, &n, json!([0, 1]));
        change(&mut body);
        body
    };
    for (body, code, field) in [
        (with(&|b| b["seeds"] = json!([])), "invalid_config", "seeds"),
        (with(&|b| b["seeds"] = json!([1, 1])), "invalid_config", "repeats"),
        (with(&|b| b["seeds"] = json!([0, 1u64 << 63])), "invalid_config", "int64"),
        (
            with(&|b| {
                b["seeds"] = Value::Null;
                b["seed_count"] = json!(0)
            }),
            "invalid_config",
            "seeds",
        ),
        (
            with(&|b| {
                b["seeds"] = json!((0..34).collect::<Vec<u64>>());
                b["algorithms"] = json!(["bc", "safedice", "dwbc"]);
            }),
            "invalid_config",
            "102 jobs",
        ),
        // Refused before a list of 2^31 seeds is made (that request used to hang the server).
        (
            with(&|b| {
                b.as_object_mut().unwrap().remove("seeds");
                b["seed_count"] = json!(2_147_483_647u32);
            }),
            "invalid_config",
            "seed_count",
        ),
        (with(&|b| b["algorithms"] = json!([])), "invalid_config", "algorithms"),
        (with(&|b| b["algorithms"] = json!(["bc", "bc"])), "invalid_config", "label"),
        (with(&|b| b["algorithms"] = json!(["nope"])), "invalid_body", "algorithms"),
        (with(&|b| b["config"] = json!({"seed": 3})), "invalid_config", "seeds"),
        (with(&|b| b["config"] = json!({"iterations": 0})), "invalid_config", "algorithms[0]"),
        (
            with(&|b| b["algorithms"] = json!([{"algorithm": "bc", "label": "has space"}])),
            "invalid_config",
            "label",
        ),
    ] {
        let response = app.post("/v1/experiments").json(&body).send().await.unwrap();
        let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, code).await;
        assert!(message.contains(field), "{field}: {message}");
    }
    let response = app
        .post("/v1/experiments")
        .json(&with(&|b| b["unlabeled_dataset"] = json!("gone")))
        .send()
        .await
        .unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    assert_eq!((app.count_rows("jobs").await, app.count_rows("experiments").await), (0, 0));
}
