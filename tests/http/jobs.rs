//! Jobs, policies and inference through the real server: train SafeDICE and BC on uploaded
//! gridworld data, follow them, query actions over /act and the KServe v2 protocol, download the
//! weights; cancel; and the exact status and code of every bad request.

use std::time::Duration;

use crate::support::app::{assert_error, assert_v2_error, TestApp};
use crate::support::jobs::*;
use futures::StreamExt;
use onnx_protobuf::Message;
use rand::SeedableRng;
use reqwest::StatusCode;
use safedice::algo::{Policy, PolicySpec};
use safedice::data::Actions;
use serde_json::{json, Value};

pub(crate) async fn upload_grid(app: &TestApp) -> (String, String) {
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;
    (u, n)
}

/// Reads server-sent events until the stream ends: (event name, data JSON) pairs.
async fn read_events(app: &TestApp, job_id: &str) -> Vec<(String, Value)> {
    events_until_the_end(open_events(app, job_id).await).await
}

/// Opens a job's event stream: once this returns, the server watches the job's events.
async fn open_events(app: &TestApp, job_id: &str) -> reqwest::Response {
    let response = app.get(&format!("/v1/jobs/{job_id}/events")).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    assert!(response.headers()["content-type"].to_str().unwrap().starts_with("text/event-stream"));
    response
}

/// The events of an open stream, read until it ends: (event name, data JSON) pairs.
async fn events_until_the_end(response: reqwest::Response) -> Vec<(String, Value)> {
    let mut text = String::new();
    let mut body = response.bytes_stream();
    while let Some(chunk) = tokio::time::timeout(Duration::from_secs(300), body.next())
        .await
        .expect("the event stream goes quiet")
    {
        text.push_str(std::str::from_utf8(&chunk.unwrap()).unwrap());
    }
    text.split("\n\n")
        .filter_map(|block| {
            let field = |name: &str| {
                block.lines().find_map(|l| l.strip_prefix(name)).map(|v| v.trim().to_owned())
            };
            Some((field("event:")?, serde_json::from_str(&field("data:")?).unwrap()))
        })
        .collect()
}

/// `POST path` with the observations as binary tensor data, asking for binary output; the
/// INT64 actions decoded from the response's binary part.
async fn binary_infer(app: &TestApp, path: &str, flat: &[f32]) -> Vec<i64> {
    let bytes: Vec<u8> = flat.iter().flat_map(|v| v.to_le_bytes()).collect();
    let header = json!({"inputs": [{"name": "observations", "datatype": "FP32",
        "shape": [flat.len() / GRID_OBS_DIM, GRID_OBS_DIM],
        "parameters": {"binary_data_size": bytes.len()}}],
        "outputs": [{"name": "actions", "parameters": {"binary_data": true}}]})
    .to_string();
    let mut body = header.clone().into_bytes();
    body.extend_from_slice(&bytes);
    let response = app
        .post(path)
        .header("inference-header-content-length", header.len())
        .header("content-type", "application/octet-stream")
        .body(body)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let length: usize =
        response.headers()["inference-header-content-length"].to_str().unwrap().parse().unwrap();
    let body = response.bytes().await.unwrap();
    let header: Value = serde_json::from_slice(&body[..length]).unwrap();
    let output = &header["outputs"][0];
    assert_eq!((output["datatype"].as_str(), output.get("data")), (Some("INT64"), None));
    let data = &body[length..];
    assert_eq!(output["parameters"]["binary_data_size"], data.len());
    data.chunks_exact(8).map(|b| i64::from_le_bytes(b.try_into().unwrap())).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn safedice_and_bc_train_and_serve_identical_actions_over_act_and_v2() {
    let app = TestApp::spawn_with(|c| c.workers = 2).await;
    let (u, n) = upload_grid(&app).await;
    let safedice = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": small_config(300, 1), "runner": {"log_every": 10, "checkpoint_every": 100}}),
    )
    .await;
    // BC needs no non-preferred dataset.
    let bc = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "bc", "unlabeled_dataset": u, "config": small_config(200, 1)}),
    )
    .await;
    assert_eq!(safedice["config"]["discriminator_iterations"], 300, "service: as many steps");
    assert_eq!(safedice["progress"]["total"], 600);
    assert_eq!(safedice["runner"], json!({"log_every": 10, "checkpoint_every": 100}));
    assert_eq!(bc["runner"]["log_every"], 100, "default runner options");

    let events = read_events(&app, safedice["id"].as_str().unwrap()).await;
    crate::openapi::assert_events_declared(&app, "/v1/jobs/{id}/events", &events).await;
    let (last_name, last_job) = events.last().unwrap();
    assert_eq!((last_name.as_str(), last_job["status"].as_str()), ("status", Some("succeeded")));
    assert_eq!(events[0].0, "status");
    for (name, data) in &events {
        if name == "progress" {
            assert!(data["step"].as_u64().unwrap() <= 600 && data["total"] == 600, "{data}");
        }
    }

    let sd =
        wait_for_status(&app.client, &app.base_url, safedice["id"].as_str().unwrap(), "succeeded")
            .await;
    let bc =
        wait_for_status(&app.client, &app.base_url, bc["id"].as_str().unwrap(), "succeeded").await;
    assert_eq!(sd["progress"]["step"], 600);
    assert_eq!(app.count_rows("job_checkpoints").await, 0, "removed once the jobs succeeded");
    assert_eq!(sd["progress"]["fraction"], 1.0);
    assert!(sd["alpha_hat"].as_f64().unwrap().is_finite(), "{sd}");
    assert!(bc["alpha_hat"].is_null());
    let listed = get_json(&app.client, &app.url("/v1/jobs?status=succeeded&limit=1")).await;
    assert_eq!((listed["total"].as_u64(), listed["items"].as_array().unwrap().len()), (Some(2), 1));
    assert_eq!(listed["next_offset"], 1);

    // Metrics: recorded every 10 steps (+ the last); downsampled on request, last point kept.
    let full = get_json(
        &app.client,
        &app.url(&format!("/v1/jobs/{}/metrics", sd["id"].as_str().unwrap())),
    )
    .await;
    assert_eq!(full["downsampled"], false);
    let rows = full["rows"].as_array().unwrap();
    let steps: std::collections::BTreeSet<u64> =
        rows.iter().map(|r| r["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, (1..=60).map(|k| k * 10).collect());
    let name = rows.last().unwrap()["name"].as_str().unwrap().to_owned();
    let series: Vec<&Value> = rows.iter().filter(|r| r["name"] == name.as_str()).collect();
    let small = get_json(
        &app.client,
        &app.url(&format!(
            "/v1/jobs/{}/metrics?names={name}&max_points=4",
            sd["id"].as_str().unwrap()
        )),
    )
    .await;
    let points = small["rows"].as_array().unwrap();
    assert!(series.len() > 4 && small["downsampled"] == true);
    assert_eq!(points.len(), 4);
    assert!(points.iter().all(|p| p["name"] == name.as_str()));
    assert_eq!(points[3], *series[series.len() - 1], "the last point is kept exactly");

    for job in [&sd, &bc] {
        let policy_id = job["policy_id"].as_str().unwrap();
        let policy = get_json(&app.client, &app.url(&format!("/v1/policies/{policy_id}"))).await;
        assert_eq!(
            (policy["job_id"].clone(), policy["obs_dim"].clone()),
            (job["id"].clone(), json!(GRID_OBS_DIM))
        );
        let discrete =
            serde_json::to_value(safedice::data::ActionSpace::Discrete { n: 4 }).unwrap();
        assert_eq!(policy["action_space"], discrete);
        assert!(policy["final_metrics"].as_object().is_some_and(|m| !m.is_empty()));

        let observations = grid_observations();
        let act = app
            .post(&format!("/v1/policies/{policy_id}/act"))
            .json(&json!({"observations": observations}))
            .send()
            .await
            .unwrap();
        assert_eq!(act.status(), StatusCode::OK);
        let actions: Value = act.json().await.unwrap();
        let actions = actions["actions"].as_array().unwrap().clone();
        assert_eq!(actions.len(), GRID_OBS_DIM);
        assert!(actions.iter().all(|a| a.as_u64().is_some_and(|a| a < 4)));

        let flat: Vec<f32> = observations.iter().flatten().copied().collect();
        let infer = app
            .post(&format!("/v2/models/{policy_id}/infer"))
            .json(&json!({"id": "r1", "inputs": [{"name": "observations", "datatype": "FP32",
                          "shape": [GRID_OBS_DIM, GRID_OBS_DIM], "data": flat}]}))
            .send()
            .await
            .unwrap();
        assert_eq!(infer.status(), StatusCode::OK);
        let infer: Value = infer.json().await.unwrap();
        assert_eq!(infer["id"], "r1");
        assert_eq!(infer["outputs"][0]["datatype"], "INT64");
        assert_eq!(infer["outputs"][0]["shape"], json!([GRID_OBS_DIM]));
        assert_eq!(infer["outputs"][0]["data"].as_array().unwrap(), &actions, "v2 == /act");
        // Open Inference Protocol clients may declare another content type, or none.
        let body = json!({"inputs": [{"name": "observations", "datatype": "FP32",
                          "shape": [GRID_OBS_DIM, GRID_OBS_DIM], "data": flat}]})
        .to_string();
        for content_type in [None, Some("text/plain"), Some("application/octet-stream")] {
            let mut request = app.post(&format!("/v2/models/{policy_id}/infer")).body(body.clone());
            if let Some(content_type) = content_type {
                request = request.header("content-type", content_type);
            }
            let response = request.send().await.unwrap();
            assert_eq!(response.status(), StatusCode::OK, "{content_type:?}");
            let answer: Value = response.json().await.unwrap();
            assert_eq!(answer["outputs"][0]["data"].as_array().unwrap(), &actions);
        }
        let broken = app.post(&format!("/v2/models/{policy_id}/infer")).body("{").send();
        assert_v2_error(broken.await.unwrap(), StatusCode::BAD_REQUEST).await;

        let meta = get_json(&app.client, &app.url(&format!("/v2/models/{policy_id}"))).await;
        assert_eq!(meta["inputs"][0]["shape"], json!([-1, GRID_OBS_DIM]));
        assert_eq!(meta["platform"], "safedice");
        let versioned = format!("/v2/models/{policy_id}/versions/1");
        assert_eq!(get_json(&app.client, &app.url(&versioned)).await, meta);
        let ready = get_json(&app.client, &app.url(&format!("{versioned}/ready"))).await;
        assert_eq!(ready["ready"], true);
        // The binary tensor data extension, both ways, on the versioned route.
        let binary = binary_infer(&app, &format!("{versioned}/infer"), &flat).await;
        assert_eq!(binary, actions.iter().map(|a| a.as_i64().unwrap()).collect::<Vec<_>>());

        // The downloaded artefact rebuilds the same policy.
        let weights = app.get(&format!("/v1/policies/{policy_id}/weights")).send().await.unwrap();
        assert_eq!(weights.status(), StatusCode::OK);
        let spec: PolicySpec =
            serde_json::from_str(weights.headers()["x-safedice-policy-spec"].to_str().unwrap())
                .unwrap();
        assert_eq!(spec, serde_json::from_value::<PolicySpec>(policy["spec"].clone()).unwrap());
        let file = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(file.path(), weights.bytes().await.unwrap()).unwrap();
        // The file alone: spec and training run in its safetensors metadata.
        let (local, metadata) = Policy::from_file(file.path()).unwrap();
        assert_eq!(metadata.spec, spec);
        assert_eq!(metadata.training["config"], job["config"]);
        assert_eq!(metadata.training["unlabeled_dataset"], job["unlabeled_dataset"]);
        assert_eq!(metadata.training["non_preferred_dataset"], job["non_preferred_dataset"]);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let Actions::Discrete(local) = local.act(&flat, true, &mut rng).unwrap() else { panic!() };
        assert_eq!(serde_json::to_value(local).unwrap(), Value::Array(actions));

        // The ONNX export (onnxruntime runs it in tests/clients): one input, the actions and
        // probabilities out, then SafeDICE's safety scores.
        let export = format!("/v1/policies/{policy_id}/export");
        let model = app.get(&format!("{export}?format=onnx")).send().await.unwrap();
        assert_eq!(model.status(), StatusCode::OK);
        let length = model.headers()["content-length"].to_str().unwrap().parse::<usize>();
        let bytes = model.bytes().await.unwrap();
        assert_eq!(length, Ok(bytes.len()), "streamed with its length announced");
        // Built from the stored weights: `safedice export` of the policy file, byte for byte.
        let file = app.get(&format!("/v1/policies/{policy_id}/weights")).send().await.unwrap();
        let file = file.bytes().await.unwrap();
        assert_eq!(safedice::algo::onnx::export_portable(file.to_vec()).unwrap(), bytes);
        let model = onnx_protobuf::ModelProto::parse_from_bytes(&bytes).expect("an ONNX model");
        assert_eq!(model.opset_import[0].version, safedice::algo::onnx::OPSET);
        let names = |v: &[onnx_protobuf::ValueInfoProto]| -> Vec<String> {
            v.iter().map(|i| i.name.clone()).collect()
        };
        assert_eq!(names(&model.graph.input), ["observations"]);
        let mut outputs = vec!["actions", "probabilities"];
        if job["algorithm"] == "safedice" {
            outputs.extend(["non_preferred_log_ratio", "out_of_support"]);
        }
        assert_eq!(names(&model.graph.output), outputs);
        let response = app.get(&format!("{export}?format=torchscript")).send().await.unwrap();
        let message = assert_error(response, StatusCode::BAD_REQUEST, "bad_request").await;
        assert!(message.contains("onnx"), "names the formats: {message}");
        let response = app.get("/v1/policies/nope/export").send().await.unwrap();
        assert_error(response, StatusCode::NOT_FOUND, "not_found").await;

        // Sampling with a seed is reproducible.
        let sample = |seed: u64| {
            app.post(&format!("/v1/policies/{policy_id}/act"))
                .json(&json!({"observations": grid_observations(), "deterministic": false, "seed": seed}))
                .send()
        };
        let a: Value = sample(7).await.unwrap().json().await.unwrap();
        let b: Value = sample(7).await.unwrap().json().await.unwrap();
        assert_eq!(a, b);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_stops_a_running_job_keeping_its_metrics_and_a_queued_one_at_once() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_grid(&app).await;
    let body = |iterations: u64| {
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": small_config(iterations, 0), "runner": {"log_every": 1}})
    };
    let running = create_job(&app.client, &app.base_url, body(ENDLESS_ITERATIONS)).await;
    let queued = create_job(&app.client, &app.base_url, body(100)).await;
    let running_id = running["id"].as_str().unwrap();
    let job = wait_for_job(&app.client, &app.base_url, running_id, Duration::from_secs(120), |j| {
        j["status"] == "running" && j["progress"]["step"].as_u64().unwrap() >= 20
    })
    .await;
    let metrics = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    assert!(metrics.lines().any(|l| l == "safedice_job_queue_depth 1"), "{metrics}");
    assert!(metrics.lines().any(|l| l == r#"safedice_jobs{status="running"} 1"#), "{metrics}");
    // The fleet: this server's worker pool is the one worker, running the job.
    let worker = job["worker"].as_str().expect("a running job names its worker");
    let has = |line: &str| metrics.lines().any(|l| l == line);
    assert!(has("safedice_workers 1"), "{metrics}");
    assert!(has(&format!(r#"safedice_running_jobs{{worker="{worker}"}} 1"#)), "{metrics}");
    assert!(has("safedice_expired_leases 0") && has("safedice_lease_takeovers 0"), "{metrics}");
    let heartbeat = format!(r#"safedice_worker_heartbeat_age_seconds{{worker="{worker}"}} "#);
    assert!(metrics.lines().any(|l| l.starts_with(&heartbeat)), "{metrics}");
    // One worker: the second job is still queued and is cancelled without running.
    let cancelled = app
        .post(&format!("/v1/jobs/{}/cancel", queued["id"].as_str().unwrap()))
        .send()
        .await
        .unwrap();
    assert_eq!(cancelled.status(), StatusCode::OK);
    let cancelled: Value = cancelled.json().await.unwrap();
    assert_eq!(
        (cancelled["status"].as_str(), cancelled["progress"]["step"].as_u64()),
        (Some("cancelled"), Some(0))
    );

    let response = app.post(&format!("/v1/jobs/{running_id}/cancel")).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let job = wait_for_status(&app.client, &app.base_url, running_id, "cancelled").await;
    assert!(job["cancel_requested"].as_bool().unwrap());
    assert!(job["policy_id"].is_null());
    let metrics =
        get_json(&app.client, &app.url(&format!("/v1/jobs/{running_id}/metrics?max_points=10000")))
            .await;
    assert!(metrics["rows"].as_array().unwrap().len() >= 20, "partial metrics stay");
    assert_eq!(app.count_rows("job_checkpoints").await, 0);
    assert_eq!(app.count_rows("policies").await, 0);

    let again = app.post(&format!("/v1/jobs/{running_id}/cancel")).send().await.unwrap();
    assert_error(again, StatusCode::CONFLICT, "job_finished").await;
    let missing = app.post("/v1/jobs/nope/cancel").send().await.unwrap();
    assert_error(missing, StatusCode::NOT_FOUND, "not_found").await;
}

/// A run that fails is ended once, by its worker, which publishes the failure: the job's event
/// stream gets it from the worker, not from the API node's poll of the jobs table (which would
/// repair a missing event within half a second, and so hides it from the stream alone). What
/// tells them apart is the worker's own log: a worker that ends the job and publishes logs
/// `job stopped` with the status; one whose end write was refused logs that another worker took
/// the job over, and publishes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_run_is_ended_once_by_its_worker_which_publishes_the_failure() {
    let worker_log = crate::support::server_log::capture();
    let app = TestApp::spawn().await;
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;
    // Observations near f32::MAX, not normalised: the first discriminator loss overflows and
    // training stops at step 0 with `Diverged` (tests/learning's non-finite guard test).
    let mut parts = unlabeled.into_parts();
    parts.observations.iter_mut().for_each(|x| *x *= 3e38);
    let overflowing = safedice::data::Dataset::new(parts).unwrap();
    let o = upload(&app.client, &app.base_url, &overflowing, "grid-overflowing").await;
    // The one worker is busy until the failing job's stream is open, so the stream sees the job
    // run and fail rather than read it already failed.
    let blocker = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "bc", "unlabeled_dataset": u,
               "config": small_config(ENDLESS_ITERATIONS, 0)}),
    )
    .await;
    let blocker = blocker["id"].as_str().unwrap();
    wait_for_status(&app.client, &app.base_url, blocker, "running").await;
    let mut config = small_config(100, 0);
    config["normalize_observations"] = json!(false);
    let failing = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": o, "non_preferred_dataset": n,
               "config": config}),
    )
    .await;
    let id = failing["id"].as_str().unwrap();
    let stream = open_events(&app, id).await;
    let cancel = app.post(&format!("/v1/jobs/{blocker}/cancel")).send().await.unwrap();
    assert_eq!(cancel.status(), StatusCode::OK);
    let events = events_until_the_end(stream).await;

    // The message is the trainer's own error, as the same training gives it here.
    let config: safedice::algo::ResolvedConfig =
        serde_json::from_value(failing["config"].clone()).unwrap();
    let data = safedice::algo::TrainingData {
        unlabeled: std::sync::Arc::new(overflowing),
        non_preferred: Some(std::sync::Arc::new(non_preferred)),
    };
    let mut trainer = safedice::algo::build_trainer(&config, &data, None).unwrap();
    let message = trainer.step(true).map(|_| ()).unwrap_err().to_string();
    assert!(message.starts_with("training diverged at step 0: "), "{message}");

    // (a) The job ended failed, with the trainer's message, and nothing of a policy.
    let job = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}"))).await;
    assert_eq!(
        (job["status"].as_str(), job["error"].as_str(), &job["policy_id"]),
        (Some("failed"), Some(message.as_str()), &Value::Null),
        "{job}"
    );
    assert_eq!(app.count_rows("job_checkpoints").await, 0);
    // (b) The stream: the job queued, then running, then failed with the message; the failure
    // is its last event (the stream ends there). Each status event carries the job as stored
    // when it is sent, so a status may come twice (the API node's follower also announces the
    // job it saw queued, at once on PostgreSQL, which notifies it), and a stream that fell
    // behind the run by the few milliseconds it lasted shows it failed where it was running.
    let mut statuses: Vec<&str> = events
        .iter()
        .filter(|(name, _)| name == "status")
        .map(|(_, job)| job["status"].as_str().unwrap())
        .collect();
    statuses.dedup();
    assert!(
        matches!(statuses[..], ["queued", "running", "failed"] | ["queued", "failed"]),
        "{statuses:?}: {events:?}"
    );
    let (name, last) = events.last().unwrap();
    assert_eq!((name.as_str(), last), ("status", &job));
    // (c) The worker ended the job and published it; it never thought the job taken over.
    let lines = worker_log.lines_of_job(id);
    let stopped: Vec<&String> = lines.iter().filter(|l| l.contains("job stopped")).collect();
    assert_eq!(stopped.len(), 1, "{lines:#?}");
    assert!(stopped[0].ends_with("job stopped status=failed"), "{lines:#?}");
    assert!(!lines.iter().any(|l| l.contains("took the job over")), "{lines:#?}");
    // The job's log has the failure once, as its last line.
    let logged = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}/logs"))).await;
    let logged: Vec<(&str, &str)> = logged
        .as_array()
        .unwrap()
        .iter()
        .map(|l| (l["level"].as_str().unwrap(), l["message"].as_str().unwrap()))
        .collect();
    let failed = format!("failed: {message}");
    assert_eq!(logged.iter().filter(|(_, m)| m.starts_with("failed: ")).count(), 1, "{logged:?}");
    assert_eq!(logged.last(), Some(&("error", failed.as_str())), "{logged:?}");
    // (d) An error that retrying cannot fix ends the job on its first attempt: no retry.
    assert_eq!((job["attempt"].as_u64(), job["max_attempts"].as_u64()), (Some(1), Some(3)));
    let attempts = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}/attempts"))).await;
    let attempts = attempts["attempts"].as_array().unwrap();
    assert_eq!(attempts.len(), 1, "{attempts:?}");
    let only = &attempts[0];
    assert_eq!(
        (only["attempt"].as_u64(), only["worker"].as_str(), only["outcome"].as_str()),
        (Some(1), job["worker"].as_str(), Some("failed"))
    );
    assert_eq!(only["message"].as_str(), Some(message.as_str()));
    assert!(only["ended_at"].is_string(), "{only}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_workers_train_two_jobs_at_the_same_time() {
    let app = TestApp::spawn_with(|c| c.workers = 2).await;
    let (u, _) = upload_grid(&app).await;
    let body = json!({"algorithm": "bc", "unlabeled_dataset": u,
                      "config": small_config(ENDLESS_ITERATIONS, 0)});
    let first = create_job(&app.client, &app.base_url, body.clone()).await;
    let second = create_job(&app.client, &app.base_url, body).await;
    let ids = [first["id"].as_str().unwrap(), second["id"].as_str().unwrap()];
    // Both advance while the other runs: each is seen running past step 50 while the other is
    // still running too.
    for (me, other) in [(ids[0], ids[1]), (ids[1], ids[0])] {
        wait_for_job(&app.client, &app.base_url, me, Duration::from_secs(120), |j| {
            j["status"] == "running" && j["progress"]["step"].as_u64().unwrap() >= 50
        })
        .await;
        let other = get_json(&app.client, &app.url(&format!("/v1/jobs/{other}"))).await;
        assert_eq!(other["status"], "running", "{other}");
    }
    let metrics = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    assert!(metrics.lines().any(|l| l == r#"safedice_jobs{status="running"} 2"#), "{metrics}");
    for id in ids {
        let response = app.post(&format!("/v1/jobs/{id}/cancel")).send().await.unwrap();
        assert_eq!(response.status(), StatusCode::OK);
        wait_for_status(&app.client, &app.base_url, id, "cancelled").await;
    }
}

#[tokio::test]
async fn bad_job_requests_get_the_exact_status_and_code_and_store_nothing() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_grid(&app).await;
    // Continuous actions: its spaces disagree with the discrete gridworld's.
    let point = crate::support::tasks::point_dataset(5, 5, 0);
    let p = upload(&app.client, &app.base_url, &point, "point").await;
    let cases = [
        (
            json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
                "config": {"iterations": 0}}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_config",
            Some("config.iterations: must be between 1 and 100000000, got 0"),
        ),
        (
            json!({"algorithm": "bc", "unlabeled_dataset": u, "config": {"seed": 1u64 << 63}}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_config",
            Some("config.seed: 9223372036854775808 is above 9223372036854775807, the largest 64-bit signed integer (seeds are int64)"),
        ),
        (
            json!({"algorithm": "bc", "unlabeled_dataset": u, "config": {"lr_nu": 0.1}}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_config",
            None,
        ),
        (
            json!({"algorithm": "safedice", "unlabeled_dataset": u}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_config",
            None,
        ),
        (
            json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": p}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_config",
            None,
        ),
        (
            json!({"algorithm": "bc", "unlabeled_dataset": u, "runner": {"log_every": 0}}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_config",
            Some("runner.log_every: must be between 1 and 1000000, got 0"),
        ),
        (
            json!({"algorithm": "bc", "unlabeled_dataset": "no-such-dataset"}),
            StatusCode::NOT_FOUND,
            "not_found",
            None,
        ),
        (
            json!({"algorithm": "sac", "unlabeled_dataset": u}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_body",
            None,
        ),
    ];
    for (body, status, code, message) in cases {
        let response = app.post("/v1/jobs").json(&body).send().await.unwrap();
        let got = assert_error(response, status, code).await;
        if let Some(message) = message {
            assert_eq!(got, message);
        }
        if code == "invalid_config" && body.get("config").is_some_and(|c| c.get("lr_nu").is_some())
        {
            assert!(got.starts_with("config.lr_nu: unknown key for algorithm bc"), "{got}");
        }
    }
    assert_eq!(app.count_rows("jobs").await, 0);
    assert_error(
        app.get("/v1/jobs/nope").send().await.unwrap(),
        StatusCode::NOT_FOUND,
        "not_found",
    )
    .await;
    assert_error(
        app.get("/v1/jobs?status=done").send().await.unwrap(),
        StatusCode::BAD_REQUEST,
        "bad_request",
    )
    .await;
}

/// A job's `threads`: as its config sets them, else the server's `--job-threads`, fewer where
/// its steps are too small to gain from another thread; out of range refused, nothing stored.
#[tokio::test]
async fn a_jobs_threads_come_from_its_config_or_the_servers_job_threads() {
    let app = TestApp::spawn_with(|c| {
        c.job_threads = Some(3);
        c.workers = 0;
    })
    .await;
    let (u, n) = upload_grid(&app).await;
    let body = |config: Value| {
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": config})
    };
    let large = json!({"hidden_sizes": [256, 256], "batch_size": 512});
    let small = json!({"hidden_sizes": [32, 32], "batch_size": 64});
    let chosen = json!({"hidden_sizes": [32, 32], "batch_size": 64, "threads": 5});
    for (config, threads) in [(large, 3), (small, 1), (chosen, 5)] {
        let response = app.post("/v1/jobs").json(&body(config.clone())).send().await.unwrap();
        assert_eq!(response.status(), StatusCode::CREATED, "{config}");
        let job: Value = response.json().await.unwrap();
        assert_eq!(job["config"]["threads"], threads, "{config}");
    }
    for bad in [0, 65] {
        let response =
            app.post("/v1/jobs").json(&body(json!({"threads": bad}))).send().await.unwrap();
        let message =
            assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_config").await;
        assert_eq!(message, format!("config.threads: must be between 1 and 64, got {bad}"));
    }
    assert_eq!(app.count_rows("jobs").await, 3);
}

#[tokio::test]
async fn bad_observations_get_the_exact_status_and_code() {
    let app = TestApp::spawn().await;
    let (u, _) = upload_grid(&app).await;
    let job = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "bc", "unlabeled_dataset": u, "config": small_config(5, 0)}),
    )
    .await;
    let job =
        wait_for_status(&app.client, &app.base_url, job["id"].as_str().unwrap(), "succeeded").await;
    let id = job["policy_id"].as_str().unwrap();
    let act = |body: Value| app.post(&format!("/v1/policies/{id}/act")).json(&body).send();
    let row = vec![0.0f64; GRID_OBS_DIM];
    let mut huge = row.clone();
    huge[3] = 1e39; // finite in JSON, infinite as a 32-bit float
    let cases = [
        (json!({"observations": []}), StatusCode::UNPROCESSABLE_ENTITY, "invalid_observations"),
        (
            json!({"observations": [[0.0, 1.0]]}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_observations",
        ),
        (json!({"observations": [huge]}), StatusCode::UNPROCESSABLE_ENTITY, "invalid_observations"),
        (json!({"observations": [[null]]}), StatusCode::UNPROCESSABLE_ENTITY, "invalid_body"),
        (
            json!({"observations": [row], "temperature": 1}),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_body",
        ),
    ];
    for (body, status, code) in cases {
        assert_error(act(body).await.unwrap(), status, code).await;
    }
    let unknown = app
        .post("/v1/policies/nope/act")
        .json(&json!({"observations": [row]}))
        .send()
        .await
        .unwrap();
    assert_error(unknown, StatusCode::NOT_FOUND, "not_found").await;
    let infer = |input: Value| {
        app.post(&format!("/v2/models/{id}/infer")).json(&json!({"inputs": [input]})).send()
    };
    let wrong_type = json!({"name": "observations", "datatype": "FP64", "shape": [1, GRID_OBS_DIM], "data": row});
    let wrong_shape =
        json!({"name": "observations", "datatype": "FP32", "shape": [1, 3], "data": [0, 0, 0]});
    let short = json!({"name": "observations", "datatype": "FP32", "shape": [2, GRID_OBS_DIM], "data": row});
    // A declared shape far beyond the data is refused from the data, allocating nothing for it.
    let huge = json!({"name": "observations", "datatype": "FP32",
        "shape": [i64::MAX / 2, GRID_OBS_DIM], "data": row});
    let no_data = json!({"name": "observations", "datatype": "FP32", "shape": [1, GRID_OBS_DIM]});
    for input in [wrong_type, wrong_shape, short, huge, no_data] {
        assert_v2_error(infer(input).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY).await;
    }
    let wrong_name =
        json!({"name": "obs", "datatype": "FP32", "shape": [1, GRID_OBS_DIM], "data": row});
    let message =
        assert_v2_error(infer(wrong_name).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(message.contains("`observations`"), "{message}");
    let missing = app.get("/v2/models/nope").send().await.unwrap();
    assert!(assert_v2_error(missing, StatusCode::NOT_FOUND).await.contains("nope"));
    let version_two = app.get(&format!("/v2/models/{id}/versions/2")).send().await.unwrap();
    assert_v2_error(version_two, StatusCode::NOT_FOUND).await;
    assert_eq!(app.get("/v2/health/ready").send().await.unwrap().status(), StatusCode::OK);
}

/// A job cancelled while queued and deleted right after: its open event stream ends, with the
/// cancelled status or the `deleted` event last (it used to wait for ever: neither the cancel
/// of a queued job nor the delete told the streams).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_event_stream_of_a_job_cancelled_then_deleted_at_once_ends() {
    let app = TestApp::spawn_with(|c| c.workers = 0).await;
    let (u, _) = upload_grid(&app).await;
    for _ in 0..3 {
        let body = json!({"algorithm": "bc", "unlabeled_dataset": u,
                          "config": small_config(ENDLESS_ITERATIONS, 0)});
        let job = create_job(&app.client, &app.base_url, body).await;
        let id = job["id"].as_str().unwrap();
        let stream = open_events(&app, id).await;
        let cancel = app.post(&format!("/v1/jobs/{id}/cancel")).send().await.unwrap();
        assert_eq!(cancel.status(), StatusCode::OK);
        let delete = app.delete(&format!("/v1/jobs/{id}")).send().await.unwrap();
        assert_eq!(delete.status(), StatusCode::NO_CONTENT);
        let events = tokio::time::timeout(Duration::from_secs(20), events_until_the_end(stream))
            .await
            .expect("the stream of a deleted job ends");
        let (name, last) = events.last().unwrap();
        let ended = match name.as_str() {
            "status" => last["status"] == "cancelled",
            "deleted" => last == &json!({"id": id}),
            _ => false,
        };
        assert!(ended, "{events:?}");
    }
}
