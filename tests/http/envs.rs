//! GET /v1/envs through the real server: every built-in environment with the spaces that
//! datagen's data and the evaluation use, behind the API token like the rest of /v1.

use crate::support::app::{assert_error, TestApp};
use reqwest::StatusCode;
use serde_json::{json, Value};

#[tokio::test]
async fn lists_the_built_in_environments_with_their_spaces() {
    let app = TestApp::spawn().await;
    let response = app.get("/v1/envs").send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let body: Value = response.json().await.unwrap();
    let items = body["items"].as_array().expect("items");
    let names: Vec<&str> = items.iter().map(|e| e["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["six-rooms", "point-goal", "cartpole-slider"]);

    // The API reports exactly what the environments are.
    for (item, info) in items.iter().zip(safedice::envs::list()) {
        assert_eq!(item["obs_dim"], json!(info.obs_dim));
        assert_eq!(item["horizon"], json!(info.horizon));
        assert_eq!(item["action_space"], serde_json::to_value(&info.action_space).unwrap());
        assert!(!item["cost"].as_str().unwrap().is_empty());
    }
    assert_eq!(items[0]["action_space"], json!({"type": "discrete", "n": 4}));
    assert_eq!(items[1]["action_space"]["type"], "continuous");
}

#[tokio::test]
async fn needs_the_token_when_one_is_set() {
    let app = TestApp::spawn_with(|c| c.api_token = Some("envs-test-token".into())).await;
    let anonymous = app.client.get(app.url("/v1/envs")).send().await.unwrap();
    assert_error(anonymous, StatusCode::UNAUTHORIZED, "unauthorized").await;
}
