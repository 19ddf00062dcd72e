//! GET /v1/vocabulary and the dashboard's copy of it (/ui/vocabulary.js) through the real
//! server: the job statuses (final or not, a success or not, with what each means) and the
//! evaluation metrics, the same in both places and in the OpenAPI document's enum.

use crate::support::app::TestApp;
use reqwest::StatusCode;
use serde_json::Value;

#[tokio::test]
async fn the_vocabulary_lists_every_status_and_metric_as_the_api_document_has_them() {
    let app = TestApp::spawn().await;
    let response = app.get("/v1/vocabulary").send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let body: Value = response.json().await.unwrap();
    let flag = |s: &Value, key: &str| s[key].as_bool().unwrap();
    let statuses: Vec<(&str, bool, bool)> = body["job_statuses"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| (s["name"].as_str().unwrap(), flag(s, "final"), flag(s, "success")))
        .collect();
    assert_eq!(
        statuses,
        [
            ("queued", false, false),
            ("running", false, false),
            ("succeeded", true, true),
            ("failed", true, false),
            ("cancelled", true, false),
            ("discarded", true, false),
        ]
    );
    assert!(body["job_statuses"].as_array().unwrap().iter().all(|s| s["meaning"].is_string()));
    let document: Value = app.get("/v1/openapi.json").send().await.unwrap().json().await.unwrap();
    let declared = &document["components"]["schemas"]["JobStatus"]["enum"];
    let names: Vec<&str> = statuses.iter().map(|(name, ..)| *name).collect();
    assert_eq!(declared, &serde_json::json!(names), "the schema's enum is the served list");

    let metrics = body["evaluation_metrics"].as_array().unwrap();
    assert_eq!(metrics.len(), 11);
    let paper: Vec<&str> = metrics
        .iter()
        .filter(|m| m["kind"] == "paper")
        .map(|m| m["key"].as_str().unwrap())
        .collect();
    assert_eq!(
        paper,
        [
            "normalized_return",
            "average_cost",
            "cost_violation_ratio",
            "cvar_cost_50",
            "cvar_cost_20",
            "cvar_cost_10",
            "cvar_cost_5"
        ]
    );
    for metric in metrics {
        let key = metric["key"].as_str().unwrap();
        assert_eq!(metric["history_name"], format!("eval/{key}"));
        let lower = metric["lower_is_better"].as_bool().unwrap();
        assert_eq!(lower, !key.contains("return") || key == "return_std", "{metric}");
    }
}

#[tokio::test]
async fn the_dashboard_script_carries_the_same_vocabulary() {
    let app = TestApp::spawn_with(|c| c.api_token = Some("vocabulary-token".into())).await;
    let script = app.client.get(app.url("/ui/vocabulary.js")).send().await.unwrap();
    assert_eq!(script.status(), StatusCode::OK, "open: the page needs it before a token");
    let text = script.text().await.unwrap();
    let table = text
        .split_once("const VOCABULARY = ")
        .and_then(|(_, rest)| rest.trim_end().strip_suffix(';'))
        .expect("the script defines VOCABULARY");
    let table: Value = serde_json::from_str(table).unwrap();
    let api: Value = app.get("/v1/vocabulary").send().await.unwrap().json().await.unwrap();
    assert_eq!(table, api);
    let anonymous = app.client.get(app.url("/v1/vocabulary")).send().await.unwrap();
    assert_eq!(anonymous.status(), StatusCode::UNAUTHORIZED);
}
