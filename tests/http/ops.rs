//! The server's operational surface through real HTTP: health, readiness, metrics, request
//! ids, the error shape of unknown routes and methods, bearer auth, CORS, start-up checks.

use crate::support::app::{assert_error, assert_v2_error, TestApp};
use reqwest::StatusCode;
use safedice::config::ServeConfig;
use safedice::server::Server;

const API_TOKEN: &str = "api-token-for-tests";
const INFERENCE_TOKEN: &str = "inference-token-for-tests";

async fn spawn_with_tokens() -> TestApp {
    TestApp::spawn_with(|c| {
        c.api_token = Some(API_TOKEN.into());
        c.inference_token = Some(INFERENCE_TOKEN.into());
    })
    .await
}

#[tokio::test]
async fn health_and_readiness_answer() {
    let app = TestApp::spawn().await;
    let health: serde_json::Value = app.get("/healthz").send().await.unwrap().json().await.unwrap();
    assert_eq!(health, serde_json::json!({"status": "ok"}));
    let ready = app.get("/readyz").send().await.unwrap();
    assert_eq!(ready.status(), StatusCode::OK);
    assert_eq!(ready.json::<serde_json::Value>().await.unwrap()["status"], "ready");
}

#[tokio::test]
async fn unknown_routes_and_methods_get_the_error_body() {
    let app = TestApp::spawn().await;
    let message =
        assert_error(app.get("/v1/nope").send().await.unwrap(), StatusCode::NOT_FOUND, "not_found")
            .await;
    assert!(message.contains("/v1/nope"), "{message}");
    assert_error(
        app.delete("/healthz").send().await.unwrap(),
        StatusCode::METHOD_NOT_ALLOWED,
        "method_not_allowed",
    )
    .await;
}

#[tokio::test]
async fn request_ids_are_generated_or_propagated() {
    let app = TestApp::spawn().await;
    let response = app.get("/healthz").send().await.unwrap();
    let generated = response.headers()["x-request-id"].to_str().unwrap();
    assert_eq!(generated.len(), 36, "a UUID, got {generated}");
    let response = app.get("/healthz").header("x-request-id", "trace-me-42").send().await.unwrap();
    assert_eq!(response.headers()["x-request-id"], "trace-me-42");
    let error = app.get("/missing").header("x-request-id", "trace-me-43").send().await.unwrap();
    assert_eq!(error.headers()["x-request-id"], "trace-me-43");
}

#[tokio::test]
async fn api_routes_need_the_bearer_token_and_operations_stay_open() {
    let app = spawn_with_tokens().await;
    let anonymous = |path: &str| app.client.get(app.url(path));

    let response = anonymous("/v1/openapi.json").send().await.unwrap();
    assert_eq!(response.headers()["www-authenticate"], "Bearer");
    assert_error(response, StatusCode::UNAUTHORIZED, "unauthorized").await;
    let wrong = anonymous("/v1/openapi.json").bearer_auth("not-the-token").send().await.unwrap();
    assert_error(wrong, StatusCode::UNAUTHORIZED, "unauthorized").await;
    let basic = anonymous("/v1/openapi.json").basic_auth("user", Some(API_TOKEN)).send().await;
    assert_error(basic.unwrap(), StatusCode::UNAUTHORIZED, "unauthorized").await;
    // Unknown /v1 routes are not revealed to anonymous callers either.
    assert_error(
        anonymous("/v1/nope").send().await.unwrap(),
        StatusCode::UNAUTHORIZED,
        "unauthorized",
    )
    .await;

    let with_token = app.get("/v1/openapi.json").send().await.unwrap();
    assert_eq!(with_token.status(), StatusCode::OK);
    let lowercase_scheme = anonymous("/v1/openapi.json")
        .header("authorization", format!("bearer {API_TOKEN}"))
        .send()
        .await
        .unwrap();
    assert_eq!(lowercase_scheme.status(), StatusCode::OK);

    for open in ["/healthz", "/readyz", "/metrics"] {
        assert_eq!(anonymous(open).send().await.unwrap().status(), StatusCode::OK, "{open}");
    }
}

#[tokio::test]
async fn the_inference_token_reaches_only_action_endpoints() {
    let app = spawn_with_tokens().await;
    let as_agent = |method: reqwest::Method, path: &str| {
        app.client.request(method, app.url(path)).bearer_auth(INFERENCE_TOKEN)
    };
    let response = as_agent(reqwest::Method::GET, "/v1/openapi.json").send().await.unwrap();
    assert_error(response, StatusCode::FORBIDDEN, "forbidden").await;
    let response = as_agent(reqwest::Method::GET, "/v1/datasets").send().await.unwrap();
    assert_error(response, StatusCode::FORBIDDEN, "forbidden").await;
    // Action routes pass auth (no policy p1, so they answer 404, not 401/403).
    let act = serde_json::json!({"observations": [[0.0]]});
    let response =
        as_agent(reqwest::Method::POST, "/v1/policies/p1/act").json(&act).send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    let infer = serde_json::json!({"inputs": []});
    let response =
        as_agent(reqwest::Method::POST, "/v2/models/p1/infer").json(&infer).send().await.unwrap();
    assert_v2_error(response, StatusCode::NOT_FOUND).await;
    // ... and stay closed to anonymous callers (in each protocol's error shape).
    let response = app.client.post(app.url("/v1/policies/p1/act")).send().await.unwrap();
    assert_error(response, StatusCode::UNAUTHORIZED, "unauthorized").await;
    let response = app.client.post(app.url("/v2/models/p1/infer")).send().await.unwrap();
    assert_v2_error(response, StatusCode::UNAUTHORIZED).await;
    let server: serde_json::Value =
        as_agent(reqwest::Method::GET, "/v2").send().await.unwrap().json().await.unwrap();
    assert_eq!(server["name"], "safedice");
    assert_eq!(
        server["extensions"],
        serde_json::json!([
            "binary_tensor_data",
            "model_repository",
            "statistics",
            "model_configuration"
        ])
    );
    // A named model's action routes are an agent's; the model repository is not.
    let response =
        as_agent(reqwest::Method::POST, "/v1/models/pilot@production/act").json(&act).send();
    assert_error(response.await.unwrap(), StatusCode::NOT_FOUND, "not_found").await;
    let response = as_agent(reqwest::Method::POST, "/v2/repository/index").send().await.unwrap();
    assert_v2_error(response, StatusCode::FORBIDDEN).await;
    let response = as_agent(reqwest::Method::PUT, "/v1/models/pilot/aliases/production").send();
    assert_error(response.await.unwrap(), StatusCode::FORBIDDEN, "forbidden").await;
    let response = as_agent(reqwest::Method::GET, "/v2/no/such/route").send().await.unwrap();
    assert_v2_error(response, StatusCode::NOT_FOUND).await;
}

#[tokio::test]
async fn metrics_count_requests_by_route_and_read_the_job_queue() {
    let app = TestApp::spawn().await;
    for _ in 0..3 {
        app.get("/healthz").send().await.unwrap();
    }
    app.get("/v1/no-such-route").send().await.unwrap();
    // No queued rows: the worker pool would claim them (and fail them, as they name no real
    // dataset). Queue depth with real jobs is checked in tests/http/jobs.rs.
    app.insert_job("job-1", "succeeded", "ds-a", None).await;
    app.insert_job("job-2", "failed", "ds-a", Some("ds-b")).await;
    app.insert_job("job-3", "running", "ds-a", None).await;

    let response = app.get("/metrics").send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    assert!(response.headers()["content-type"]
        .to_str()
        .unwrap()
        .starts_with("application/openmetrics-text"));
    let text = response.text().await.unwrap();
    let has = |line: &str| text.lines().any(|l| l == line);
    assert!(
        has(r#"safedice_http_requests_total{method="GET",route="/healthz",status="200"} 3"#),
        "{text}"
    );
    assert!(
        has(r#"safedice_http_requests_total{method="GET",route="unmatched",status="404"} 1"#),
        "{text}"
    );
    assert!(
        has(
            r#"safedice_http_request_duration_seconds_count{method="GET",route="/healthz",status="200"} 3"#
        ),
        "{text}"
    );
    assert!(text.contains(r#"safedice_http_request_duration_seconds_bucket{le="+Inf",method="GET",route="/healthz",status="200"} 3"#), "{text}");
    assert!(has("safedice_job_queue_depth 0"), "{text}");
    assert!(has(r#"safedice_jobs{status="queued"} 0"#), "{text}");
    assert!(has(r#"safedice_jobs{status="running"} 1"#), "{text}");
    assert!(has(r#"safedice_jobs{status="succeeded"} 1"#), "{text}");
    assert!(has(r#"safedice_jobs{status="failed"} 1"#), "{text}");
    assert!(text.trim_end().ends_with("# EOF"));
}

#[tokio::test]
async fn cors_preflight_answers_configured_origins_only() {
    let app = TestApp::spawn_with(|c| {
        c.api_token = Some(API_TOKEN.into());
        c.cors_origins = vec!["https://dash.example.com".into()];
    })
    .await;
    let preflight = |origin: &str| {
        app.client
            .request(reqwest::Method::OPTIONS, app.url("/v1/datasets"))
            .header("origin", origin)
            .header("access-control-request-method", "POST")
            .header("access-control-request-headers", "authorization")
    };
    let allowed = preflight("https://dash.example.com").send().await.unwrap();
    assert_eq!(allowed.status(), StatusCode::OK);
    assert_eq!(allowed.headers()["access-control-allow-origin"], "https://dash.example.com");
    let other = preflight("https://evil.example.com").send().await.unwrap();
    assert!(other.headers().get("access-control-allow-origin").is_none());
}

#[tokio::test]
async fn a_public_bind_without_a_token_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = ServeConfig::new(dir.path());
    config.bind = "0.0.0.0:0".parse().unwrap();
    let error = Server::start(config.clone()).await.err().expect("refused");
    assert!(error.to_string().contains("--api-token"), "{error}");
    config.insecure_public = true;
    let server = Server::start(config).await.expect("explicit opt-out starts");
    server.stop().await.unwrap();
}

#[tokio::test]
async fn restart_keeps_the_database_and_clears_interrupted_uploads() {
    let mut app = TestApp::spawn().await;
    // Finished, so the worker pool leaves it alone (a queued job naming no real dataset would
    // be claimed and failed).
    app.insert_job("job-1", "succeeded", "ds-a", None).await;
    let leftover = app.data_dir().join("tmp").join("upload-interrupted");
    std::fs::write(&leftover, b"half an upload").unwrap();
    app.restart().await;
    assert!(!leftover.exists(), "interrupted upload survived the restart");
    assert_eq!(app.count_rows("jobs").await, 1);
    let text = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    assert!(text.lines().any(|l| l == r#"safedice_jobs{status="succeeded"} 1"#), "{text}");
    if app.is_postgres() {
        // A process stopped inside a transaction must not hold its row locks for ever (a
        // claim skips locked rows): the store's sessions end such transactions.
        let store = app.store().await;
        let timeout: String = sqlx::query_scalar("SHOW idle_in_transaction_session_timeout")
            .fetch_one(store.pool())
            .await
            .unwrap();
        assert_eq!(timeout, "5s");
    } else {
        let journal: String =
            sqlx::query_scalar("PRAGMA journal_mode").fetch_one(&mut app.db().await).await.unwrap();
        assert_eq!(journal, "wal");
    }
}

/// `--max-streams` caps the open event streams: one more is a 503 `too_many_streams` with
/// Retry-After (while plain requests still answer), and closing a stream frees its slot. A log
/// follower resumes after the `Last-Event-ID` it sends.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn event_streams_are_capped_and_a_closed_one_frees_its_slot() {
    use crate::support::jobs::*;
    let app = TestApp::spawn_with(|c| c.max_streams = 2).await;
    let u = upload(&app.client, &app.base_url, &grid_datasets().0, "grid").await;
    let body = serde_json::json!({"algorithm": "bc", "unlabeled_dataset": u,
                                  "config": small_config(ENDLESS_ITERATIONS, 0)});
    let job = create_job(&app.client, &app.base_url, body).await;
    let id = job["id"].as_str().unwrap();
    wait_for_status(&app.client, &app.base_url, id, "running").await;
    let open = |path: String| app.get(&path).send();
    let events = open(format!("/v1/jobs/{id}/events")).await.unwrap();
    let logs = open(format!("/v1/jobs/{id}/logs?follow=true")).await.unwrap();
    assert_eq!((events.status(), logs.status()), (StatusCode::OK, StatusCode::OK));
    let refused = open(format!("/v1/jobs/{id}/events")).await.unwrap();
    assert_eq!(refused.headers()["retry-after"], "1");
    assert_error(refused, StatusCode::SERVICE_UNAVAILABLE, "too_many_streams").await;
    assert_eq!(app.get("/healthz").send().await.unwrap().status(), StatusCode::OK);
    drop(events);
    let started = std::time::Instant::now();
    loop {
        let again = open(format!("/v1/jobs/{id}/events")).await.unwrap();
        if again.status() == StatusCode::OK {
            break;
        }
        assert!(started.elapsed() < std::time::Duration::from_secs(10), "the slot stayed taken");
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    drop(logs);
    // A follower reconnecting with Last-Event-ID 1 gets the lines after the first, each with
    // its seq as event id, until the job has ended.
    app.post(&format!("/v1/jobs/{id}/cancel")).send().await.unwrap();
    let lines = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}/logs"))).await;
    let lines = lines.as_array().unwrap().len();
    assert!(lines >= 2, "claimed, started, cancelled");
    let resumed = app
        .get(&format!("/v1/jobs/{id}/logs?follow=true"))
        .header("last-event-id", "1")
        .send()
        .await
        .unwrap();
    let text = resumed.text().await.unwrap();
    let ids: Vec<&str> =
        text.lines().filter_map(|l| l.strip_prefix("id:")).map(str::trim).collect();
    let expected: Vec<String> = (2..=lines).map(|seq| seq.to_string()).collect();
    assert_eq!(ids, expected, "{text}");
}
