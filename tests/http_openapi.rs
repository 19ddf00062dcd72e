//! The committed API description (api/openapi.yaml) must be what the code generates, and the
//! server must serve the same document. Regenerate after changing a handler:
//! `UPDATE_OPENAPI=1 cargo test --test http_openapi` (or `safedice openapi > api/openapi.yaml`).

mod common;

use common::TestApp;

const COMMITTED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/api/openapi.yaml");

#[test]
fn committed_openapi_yaml_is_up_to_date() {
    let generated = safedice::http::openapi::yaml().expect("the description serializes");
    if std::env::var_os("UPDATE_OPENAPI").is_some() {
        std::fs::write(COMMITTED, &generated).expect("write api/openapi.yaml");
        return;
    }
    let committed = std::fs::read_to_string(COMMITTED).unwrap_or_default();
    assert!(
        committed == generated,
        "api/openapi.yaml is stale: regenerate it with `UPDATE_OPENAPI=1 cargo test --test \
         http_openapi` and commit the result"
    );
}

#[tokio::test]
async fn the_served_description_is_the_generated_one_and_covers_every_route() {
    let app = TestApp::spawn().await;
    let served: serde_json::Value =
        app.get("/v1/openapi.json").send().await.unwrap().json().await.unwrap();
    let generated = serde_json::to_value(safedice::http::openapi()).unwrap();
    assert_eq!(served, generated);
    let paths = served["paths"].as_object().unwrap();
    for path in ["/healthz", "/readyz", "/metrics", "/v1/openapi.json"] {
        assert!(paths.contains_key(path), "{path} missing from the description");
    }
    // /v1 operations carry the bearer requirement, operational routes do not.
    assert_eq!(
        served["paths"]["/v1/openapi.json"]["get"]["security"][0]["bearer"],
        serde_json::json!([])
    );
    assert!(served["paths"]["/healthz"]["get"].get("security").is_none());
    assert!(served["components"]["schemas"]["ErrorBody"].is_object());
}
