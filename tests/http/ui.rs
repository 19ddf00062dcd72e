//! The dashboard's routes through the real server: the page and its embedded assets are served
//! without a token (the pages send the user's token to /v1 themselves), with every script and
//! stylesheet the page names. What the pages do in a browser is tested in tests/browser/.

use crate::support::app::TestApp;
use reqwest::{header, StatusCode};

#[tokio::test]
async fn the_dashboard_and_its_assets_are_served_without_a_token() {
    let app = TestApp::spawn_with(|c| c.api_token = Some("dashboard-test-token".into())).await;
    let anonymous = |path: &str| app.client.get(app.url(path)).send();

    let index = anonymous("/").await.unwrap();
    assert_eq!(index.status(), StatusCode::OK);
    assert_eq!(index.headers()[header::CONTENT_TYPE], "text/html; charset=utf-8");
    let html = index.text().await.unwrap();
    // Nothing the page loads comes from another origin, and everything it loads is served.
    assert!(!html.contains("http://") && !html.contains("https://"));
    let loaded: Vec<&str> = html.split(['"']).filter(|part| part.starts_with("/ui/")).collect();
    assert!(loaded.len() >= 7, "{loaded:?}");
    for path in loaded {
        let response = anonymous(path).await.unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{path}");
    }

    for (path, content_type, marker) in [
        ("/ui/app.js", "text/javascript; charset=utf-8", "function route()"),
        ("/ui/algorithms.js", "text/javascript; charset=utf-8", "const ALGORITHM_TABLE = ["),
        ("/ui/style.css", "text/css; charset=utf-8", ".badge"),
        ("/ui/favicon.svg", "image/svg+xml", "<svg"),
        ("/ui/lib.js", "text/javascript; charset=utf-8", "async function api("),
        ("/ui/charts.js", "text/javascript; charset=utf-8", "function lineChart("),
        ("/ui/models.js", "text/javascript; charset=utf-8", "function modelsPage("),
        ("/ui/job_form.js", "text/javascript; charset=utf-8", "function jobForm("),
        ("/ui/compare.js", "text/javascript; charset=utf-8", "function comparePage("),
        ("/ui/experiments.js", "text/javascript; charset=utf-8", "function experimentsPage("),
        ("/ui/policies.js", "text/javascript; charset=utf-8", "function policyPage("),
        ("/ui/vendor/uPlot.iife.min.js", "text/javascript; charset=utf-8", "uPlot (v1.6.32)"),
        ("/ui/vendor/uPlot.LICENSE", "text/plain; charset=utf-8", "MIT License"),
    ] {
        let response = anonymous(path).await.unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{path}");
        assert_eq!(response.headers()[header::CONTENT_TYPE], content_type, "{path}");
        assert!(response.text().await.unwrap().contains(marker), "{path}");
    }
    // The API itself still needs the token.
    assert_eq!(anonymous("/v1/datasets").await.unwrap().status(), StatusCode::UNAUTHORIZED);
}
