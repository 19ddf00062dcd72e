//! `safedice demo` end to end through the real server: datasets uploaded over HTTP, SafeDICE and
//! BC trained as jobs, both policies evaluated through `POST /v1/policies/{id}/evaluate`.

use safedice::algo::Algorithm;
use safedice::demo::{self, DemoArgs};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn demo_trains_safedice_and_bc_over_http_and_evaluates_both() {
    let args = DemoArgs::new("six-rooms", 60, 20);
    let rows = demo::run(&args).await.unwrap();
    assert_eq!(
        rows.iter().map(|r| r.algorithm).collect::<Vec<_>>(),
        [Algorithm::Safedice, Algorithm::Bc]
    );
    for row in &rows {
        assert_eq!(row.episodes, 20);
        let m = &row.metrics;
        assert!(m.normalized_return.is_finite() && m.average_cost.is_finite(), "{row:?}");
        assert_eq!(row.alpha_hat.is_some(), row.algorithm == Algorithm::Safedice, "{row:?}");
    }
    assert!(rows[0].alpha_hat.unwrap() >= 0.0);
}

/// `safedice demo --serve`: after the demo the service stays up with the demo's named jobs, the
/// dashboard answers, and SIGTERM stops it cleanly with the data left in `--data-dir`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn demo_serve_keeps_the_service_and_its_data() {
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};

    let dir = tempfile::tempdir().unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut child = Command::new(env!("CARGO_BIN_EXE_safedice"))
        .args(["demo", "--serve", "--iterations", "60", "--episodes", "20"])
        .args(["--bind", &format!("127.0.0.1:{port}")])
        .arg("--data-dir")
        .arg(dir.path())
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .expect("start safedice demo --serve");
    let stdout = child.stdout.take().unwrap();
    let waiting = tokio::task::spawn_blocking(move || {
        let mut seen = Vec::new();
        for line in BufReader::new(stdout).lines() {
            let line = line.unwrap();
            let done = line.starts_with("The service keeps running");
            seen.push(line);
            if done {
                return seen;
            }
        }
        panic!("the demo ended without serving: {seen:#?}");
    });
    // The reader is dropped here, so the pipe is closed while the demo serves: like `| head`,
    // that must not stop the service (the stopping line below goes to a closed pipe).
    let output = tokio::time::timeout(std::time::Duration::from_secs(240), waiting)
        .await
        .expect("the demo finishes")
        .unwrap();
    let base = format!("http://127.0.0.1:{port}");
    assert!(output.last().unwrap().contains(&format!("open {base}/ in a browser")), "{output:?}");
    let jobs: serde_json::Value =
        reqwest::get(format!("{base}/v1/jobs?tag=demo")).await.unwrap().json().await.unwrap();
    let mut names: Vec<&str> =
        jobs["items"].as_array().unwrap().iter().map(|j| j["name"].as_str().unwrap()).collect();
    names.sort();
    assert_eq!(names, ["demo BC on six-rooms", "demo SafeDICE on six-rooms"]);
    let dashboard = reqwest::get(format!("{base}/")).await.unwrap();
    assert_eq!(dashboard.status(), reqwest::StatusCode::OK);

    let pid = child.id().to_string();
    assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
    let status = child.wait().unwrap();
    assert!(status.success(), "{status}");
    assert!(dir.path().join("data/safedice.sqlite").exists(), "the data stays");
}
