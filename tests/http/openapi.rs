//! The committed API description (api/openapi.yaml) must be what the code generates, and the
//! server must serve the same document. Regenerate after changing a handler:
//! `UPDATE_OPENAPI=1 cargo test --test http openapi::` (or `safedice openapi > api/openapi.yaml`).

use crate::support::app::TestApp;

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
         http openapi::` and commit the result"
    );
}

#[tokio::test]
async fn without_a_token_the_served_description_claims_no_authentication() {
    let app = TestApp::spawn().await;
    let served: serde_json::Value =
        app.get("/v1/openapi.json").send().await.unwrap().json().await.unwrap();
    let generated: serde_json::Value =
        serde_json::from_str(&safedice::http::openapi::json(false)).unwrap();
    assert_eq!(served, generated);
    assert!(served["components"].get("securitySchemes").is_none(), "{}", served["components"]);
    for (path, item) in served["paths"].as_object().unwrap() {
        for (method, operation) in item.as_object().unwrap() {
            assert!(operation.get("security").is_none(), "{method} {path} claims security");
            let responses = operation["responses"].as_object().unwrap();
            assert!(!responses.contains_key("401"), "{method} {path} documents 401");
        }
    }
}

#[tokio::test]
async fn shared_errors_are_documented_where_they_can_happen() {
    let doc = serde_json::to_value(safedice::http::openapi()).unwrap();
    let responses = |path: &str, method: &str| -> Vec<String> {
        doc["paths"][path][method]["responses"].as_object().unwrap().keys().cloned().collect()
    };
    let create_job = responses("/v1/jobs", "post");
    for status in ["400", "401", "403", "413", "415", "422", "503", "507"] {
        assert!(create_job.contains(&status.to_owned()), "POST /v1/jobs lacks {status}");
    }
    let upload = responses("/v1/datasets", "post");
    for status in ["400", "401", "408", "413", "422", "503", "507"] {
        assert!(upload.contains(&status.to_owned()), "POST /v1/datasets lacks {status}");
    }
    let list = responses("/v1/datasets", "get");
    assert!(list.contains(&"400".to_owned()) && !list.contains(&"507".to_owned()), "{list:?}");
    assert!(!responses("/healthz", "get").contains(&"401".to_owned()));
}

#[tokio::test]
async fn the_served_description_is_the_generated_one_and_covers_every_route() {
    let app = TestApp::spawn_with(|c| c.api_token = Some("s3cret".into())).await;
    let served: serde_json::Value =
        app.get("/v1/openapi.json").send().await.unwrap().json().await.unwrap();
    let generated: serde_json::Value =
        serde_json::from_str(&safedice::http::openapi::json(true)).unwrap();
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

/// Every create points at its resource's operations with OpenAPI links (what clients and
/// schemathesis's stateful phase follow), spelled as OpenAPI spells them.
#[test]
fn creates_link_to_the_operations_of_what_they_created() {
    let yaml = safedice::http::openapi::yaml().unwrap();
    assert!(!yaml.contains("operation_id"), "a link field in utoipa's spelling");
    let doc: serde_json::Value =
        serde_json::from_str(&safedice::http::openapi::json(true)).unwrap();
    let links =
        |path: &str, status: &str| doc["paths"][path]["post"]["responses"][status]["links"].clone();
    let datasets = links("/v1/datasets", "201");
    assert_eq!(datasets["get_dataset"]["operationId"], "get_dataset");
    assert_eq!(datasets["delete_dataset"]["parameters"]["id"], "$response.body#/id");
    assert_eq!(links("/v1/jobs", "201")["cancel_job"]["parameters"]["id"], "$response.body#/id");
    assert_eq!(
        links("/v1/models", "201")["get_model"]["parameters"]["name"],
        "$response.body#/name"
    );
    let version = links("/v1/models/{name}/versions", "201");
    assert_eq!(version["get_version"]["parameters"]["name"], "$request.path.name");
    assert_eq!(version["get_version"]["parameters"]["version"], "$response.body#/version");
    let evaluation = links("/v1/policies/{id}/evaluate", "202");
    assert_eq!(evaluation["get_evaluation"]["parameters"]["id"], "$response.body#/id");
    // Every link names an operation of the document.
    let operations: Vec<&str> = doc["paths"]
        .as_object()
        .unwrap()
        .values()
        .flat_map(|item| item.as_object().unwrap().values())
        .filter_map(|op| op["operationId"].as_str())
        .collect();
    let mut count = 0;
    for item in doc["paths"].as_object().unwrap().values() {
        for response in item["post"]["responses"].as_object().into_iter().flat_map(|r| r.values()) {
            for link in response["links"].as_object().into_iter().flat_map(|l| l.values()) {
                assert!(operations.contains(&link["operationId"].as_str().unwrap()), "{link}");
                count += 1;
            }
        }
    }
    assert!(count >= 30, "{count} links");
}

/// Checks each (event, JSON data) a stream sent against what the served document declares for
/// the stream at `path` (its `itemSchema`): the event is declared, and its data has every
/// property the schema requires and none it does not list.
pub(crate) async fn assert_events_declared(
    app: &TestApp,
    path: &str,
    events: &[(String, serde_json::Value)],
) {
    let doc: serde_json::Value =
        app.get("/v1/openapi.json").send().await.unwrap().json().await.unwrap();
    let declared = &doc["paths"][path]["get"]["responses"]["200"]["content"]["text/event-stream"]
        ["itemSchema"]["oneOf"];
    assert!(declared.is_array(), "{path} declares its events");
    assert!(!events.is_empty());
    let schema_of = |event: &str| {
        let each = declared.as_array().unwrap().iter();
        let declared = each.map(|e| &e["properties"]).find(|p| p["event"]["const"] == event)?;
        declared["data"]["contentSchema"]["$ref"].as_str()
    };
    for (event, data) in events {
        let reference = schema_of(event);
        let reference = reference.unwrap_or_else(|| panic!("{path}: event {event} undeclared"));
        let name = reference.trim_start_matches("#/components/schemas/");
        let schema = &doc["components"]["schemas"][name];
        let data = data.as_object().unwrap_or_else(|| panic!("{event}: {data}"));
        for required in schema["required"].as_array().into_iter().flatten() {
            let required = required.as_str().unwrap();
            assert!(data.contains_key(required), "{event} ({name}) lacks {required}: {data:?}");
        }
        let properties = schema["properties"].as_object().expect("an object schema");
        for key in data.keys() {
            assert!(properties.contains_key(key), "{event} ({name}): {key} undeclared");
        }
    }
}
