//! The dashboard's routes through the real server: the page and its embedded assets are served
//! without a token (the pages send the user's token to /v1 themselves), and the chart renderers
//! answer SVG for good input and the usual error body for bad input. What the pages do in a
//! browser is tested in tests/browser/.

use crate::support::app::{assert_error, TestApp};
use reqwest::{header, StatusCode};
use serde_json::json;

#[tokio::test]
async fn the_dashboard_and_its_assets_are_served_without_a_token() {
    let app = TestApp::spawn_with(|c| c.api_token = Some("dashboard-test-token".into())).await;
    let anonymous = |path: &str| app.client.get(app.url(path)).send();

    let index = anonymous("/").await.unwrap();
    assert_eq!(index.status(), StatusCode::OK);
    assert_eq!(index.headers()[header::CONTENT_TYPE], "text/html; charset=utf-8");
    let html = index.text().await.unwrap();
    assert!(html.contains(r#"<script src="/ui/algorithms.js" defer></script>"#));
    assert!(html.contains(r#"<script src="/ui/app.js" defer></script>"#));
    assert!(html.contains(r#"href="/ui/style.css""#));
    // Nothing the page loads comes from another origin.
    assert!(!html.contains("http://") && !html.contains("https://"));

    for (path, content_type, marker) in [
        ("/ui/app.js", "text/javascript; charset=utf-8", "function route()"),
        ("/ui/algorithms.js", "text/javascript; charset=utf-8", "const ALGORITHM_TABLE = ["),
        ("/ui/style.css", "text/css; charset=utf-8", ".badge"),
        ("/ui/favicon.svg", "image/svg+xml", "<svg"),
    ] {
        let response = anonymous(path).await.unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{path}");
        assert_eq!(response.headers()[header::CONTENT_TYPE], content_type, "{path}");
        assert!(response.text().await.unwrap().contains(marker), "{path}");
    }
    // The API itself still needs the token.
    assert_eq!(anonymous("/v1/datasets").await.unwrap().status(), StatusCode::UNAUTHORIZED);
}

#[tokio::test]
async fn the_chart_renderers_answer_svg_and_reject_bad_input_with_the_error_body() {
    let app = TestApp::spawn().await;
    let line = app
        .post("/ui/charts/line")
        .json(&json!({"title": "Losses", "x_label": "step", "y_label": "loss", "series": [
            {"name": "policy_loss", "points": [[0, 1.0], [100, 0.5], [200, 0.25]], "color": "#2563eb"}
        ]}))
        .send()
        .await
        .unwrap();
    assert_eq!(line.status(), StatusCode::OK);
    assert_eq!(line.headers()[header::CONTENT_TYPE], "image/svg+xml");
    let svg = line.text().await.unwrap();
    assert!(svg.contains(r#"data-series="policy_loss" data-points="3""#), "{svg}");

    let scatter = app
        .post("/ui/charts/scatter")
        .json(
            &json!({"title": "Cost vs return", "x_label": "cost", "y_label": "return", "points": [
                {"label": "a", "x": 1.0, "y": 2.0, "group": "SafeDICE", "color": "#2563eb"},
                {"label": "b", "x": 3.0, "y": 1.0, "group": "BC", "color": "#6b7280"}
            ]}),
        )
        .send()
        .await
        .unwrap();
    assert_eq!(scatter.status(), StatusCode::OK);
    assert_eq!(scatter.text().await.unwrap().matches(r#"<g class="point""#).count(), 2);

    let malformed = app.post("/ui/charts/line").json(&json!({"title": "no series"})).send();
    assert_error(malformed.await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_body").await;

    let too_many: Vec<[f64; 2]> =
        (0..=safedice::http::ui::MAX_CHART_POINTS).map(|i| [i as f64, 0.0]).collect();
    let huge = app
        .post("/ui/charts/line")
        .json(&json!({"title": "t", "x_label": "x", "y_label": "y", "series": [{"name": "s", "points": too_many}]}))
        .send();
    let message =
        assert_error(huge.await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "chart_too_large")
            .await;
    assert!(message.contains("at most 50000 points"), "{message}");
}
