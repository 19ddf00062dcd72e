//! GET /v1/algorithms and the dashboard's copy of it (/ui/algorithms.js) through the real
//! server: one table of names, colours and preset values, the same in both places, and a job
//! that names only a preset resolves to exactly that preset's listed values.

use crate::support::app::{assert_error, TestApp};
use reqwest::StatusCode;
use serde_json::{json, Value};

#[tokio::test]
async fn lists_every_algorithm_with_its_presets_resolved() {
    let app = TestApp::spawn().await;
    let response = app.get("/v1/algorithms").send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let body: Value = response.json().await.unwrap();
    let items = body["items"].as_array().expect("items");
    let names: Vec<&str> = items.iter().map(|a| a["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["safedice", "bc", "dwbc", "ppl", "dexperts"]);
    let safedice = &items[0];
    assert_eq!(safedice["label"], "SafeDICE");
    assert_eq!(
        safedice["color"],
        safedice::charts::algorithm_color(safedice::algo::Algorithm::Safedice)
    );
    assert_eq!(safedice["needs_non_preferred"], true);
    assert_eq!(items[1]["needs_non_preferred"], false);
    for algorithm in items {
        let presets: Vec<&str> = algorithm["presets"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["name"].as_str().unwrap())
            .collect();
        assert_eq!(presets, ["service", "paper", "authors-code"], "{}", algorithm["name"]);
    }
    // Each listed preset is what resolve_config makes of `{"preset": name}`.
    for preset in safedice["presets"].as_array().unwrap() {
        let resolved = safedice::algo::resolve_config(
            safedice::algo::Algorithm::Safedice,
            &json!({ "preset": preset["name"] }),
        )
        .unwrap();
        assert_eq!(preset["config"], serde_json::to_value(resolved).unwrap());
    }
}

#[tokio::test]
async fn the_dashboard_script_carries_the_same_table() {
    let app = TestApp::spawn_with(|c| c.api_token = Some("algorithms-token".into())).await;
    // The page needs the table before a token is entered: the asset is open.
    let script = app.client.get(app.url("/ui/algorithms.js")).send().await.unwrap();
    assert_eq!(script.status(), StatusCode::OK);
    let content_type = script.headers()["content-type"].to_str().unwrap().to_owned();
    assert!(content_type.starts_with("text/javascript"), "{content_type}");
    let text = script.text().await.unwrap();
    let table = text
        .split_once("const ALGORITHM_TABLE = ")
        .and_then(|(_, rest)| rest.trim_end().strip_suffix(';'))
        .expect("the script defines ALGORITHM_TABLE");
    let table: Value = serde_json::from_str(table).unwrap();
    let api: Value = app.get("/v1/algorithms").send().await.unwrap().json().await.unwrap();
    assert_eq!(table, api["items"]);
    // /v1 stays behind the token.
    let anonymous = app.client.get(app.url("/v1/algorithms")).send().await.unwrap();
    assert_eq!(anonymous.status(), StatusCode::UNAUTHORIZED);
}

/// The plan of a configuration is what a job created with it stores and reports, for every
/// algorithm; a configuration a job would be refused for is refused the same way.
#[tokio::test]
async fn a_plan_is_what_a_job_with_the_same_config_runs() {
    use crate::support::jobs::{create_job, grid_datasets, small_config, upload};
    let app = TestApp::spawn().await;
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "u.jsonl").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "n.jsonl").await;
    for algorithm in ["safedice", "bc", "dwbc", "ppl", "dexperts"] {
        let config = small_config(300, 1);
        let response = app
            .post(&format!("/v1/algorithms/{algorithm}/plan"))
            .json(&config)
            .send()
            .await
            .unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{algorithm}");
        let plan: Value = response.json().await.unwrap();
        let job = create_job(
            &app.client,
            &app.base_url,
            json!({"algorithm": algorithm, "unlabeled_dataset": u, "non_preferred_dataset": n,
                   "config": config}),
        )
        .await;
        let steps = &plan["steps"];
        assert_eq!(steps["total_steps"], job["progress"]["total"], "{algorithm}");
        assert_eq!(steps["pretraining_steps"], job["pretraining_steps"], "{algorithm}");
        assert_eq!(steps["iterations"], 300, "{algorithm}");
        let has_phase = job["pretraining_steps"].as_u64().unwrap() > 0;
        assert_eq!(steps["pretraining_phase"].is_string(), has_phase, "{algorithm}");
        // The job may pick its threads from the data; every other knob is the plan's.
        let (mut planned, mut stored) = (plan["config"].clone(), job["config"].clone());
        planned.as_object_mut().unwrap().remove("threads");
        stored.as_object_mut().unwrap().remove("threads");
        assert_eq!(planned, stored, "{algorithm}");
    }
    let jobs_before = app.count_rows("jobs").await;
    let bad = app.post("/v1/algorithms/safedice/plan").json(&json!({"batch": 5})).send().await;
    let message =
        assert_error(bad.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_config").await;
    assert!(message.contains("config.batch: unknown key"), "{message}");
    let not_object = app.post("/v1/algorithms/bc/plan").json(&json!([1])).send().await;
    assert_error(not_object.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_body").await;
    let unknown = app.post("/v1/algorithms/gail/plan").json(&json!({})).send().await;
    assert_error(unknown.unwrap(), StatusCode::NOT_FOUND, "not_found").await;
    assert_eq!(app.count_rows("jobs").await, jobs_before, "a plan stores no job");
}

/// An algorithm added to the registry is documented where users read about configurations: the
/// CreateJob schema's `config` names it and every key of its configuration. (The dashboard's
/// form, `/v1/algorithms`, the benchmarks' rows and step FLOPs, and the memory estimate read the
/// registry or match on it exhaustively, so the compiler holds those.)
#[test]
fn the_create_job_doc_names_every_algorithm_and_each_of_its_keys() {
    let doc: Value = serde_json::from_str(&safedice::http::openapi::json(true)).unwrap();
    let config = &doc["components"]["schemas"]["CreateJob"]["properties"]["config"];
    let text = config["description"].as_str().expect("CreateJob.config has a description");
    for algorithm in safedice::algo::Algorithm::ALL {
        let name = algorithm.spec().name;
        assert!(text.contains(&format!("`{name}`:")), "the doc does not name `{name}`");
        for key in safedice::algo::config_keys(algorithm) {
            assert!(text.contains(&format!("`{key}`")), "`{name}`'s key `{key}` is undocumented");
        }
    }
}
