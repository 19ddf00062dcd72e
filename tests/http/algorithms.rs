//! GET /v1/algorithms and the dashboard's copy of it (/ui/algorithms.js) through the real
//! server: one table of names, colours and preset values, the same in both places, and a job
//! that names only a preset resolves to exactly that preset's listed values.

use crate::support::app::TestApp;
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
