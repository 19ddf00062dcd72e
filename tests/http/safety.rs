//! Safety scores through the real server: a SafeDICE policy answers them on `/act`
//! (`safety_score: true`), on `/v2/.../infer` (parameter `safety_score`, or the outputs by name,
//! JSON and binary) and by model name, the same numbers everywhere; its metadata lists the two
//! outputs, and a named model's version counts the scores it answered in its statistics. A BC
//! policy lists none and answers 422 `safety_score_unavailable` on every route.

use crate::support::app::{assert_error, assert_v2_error, TestApp};
use crate::support::jobs::*;
use reqwest::StatusCode;
use serde_json::{json, Value};

const SAFETY_OUTPUTS: [&str; 2] = ["non_preferred_log_ratio", "out_of_support"];

async fn trained(app: &TestApp, algorithm: &str, u: &str, n: &str) -> String {
    let mut body = json!({"algorithm": algorithm, "unlabeled_dataset": u,
                          "config": small_config(80, 3)});
    if algorithm == "safedice" {
        body["non_preferred_dataset"] = json!(n);
        body["config"]["discriminator_iterations"] = json!(40);
    }
    let job = create_job(&app.client, &app.base_url, body).await;
    let done =
        wait_for_status(&app.client, &app.base_url, job["id"].as_str().unwrap(), "succeeded").await;
    done["policy_id"].as_str().unwrap().to_owned()
}

async fn post(app: &TestApp, path: &str, body: Value) -> reqwest::Response {
    app.post(path).json(&body).send().await.unwrap()
}

async fn ok_json(response: reqwest::Response) -> Value {
    let status = response.status();
    let body: Value = response.json().await.unwrap();
    assert_eq!(status, StatusCode::OK, "{body}");
    body
}

fn infer_body(observations: &[Vec<f32>], extra: Value) -> Value {
    let flat: Vec<f32> = observations.iter().flatten().copied().collect();
    let mut body = json!({"inputs": [{"name": "observations", "datatype": "FP32",
        "shape": [observations.len(), GRID_OBS_DIM], "data": flat}]});
    body.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
    body
}

fn floats(value: &Value) -> Vec<f32> {
    value.as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn safedice_policies_answer_safety_scores_everywhere_and_others_say_they_cannot() {
    let app = TestApp::spawn_with(|c| c.workers = 2).await;
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-unsafe").await;
    let safedice = trained(&app, "safedice", &u, &n).await;
    let bc = trained(&app, "bc", &u, &n).await;
    let observations = grid_observations();
    let rows = observations.len();

    // /act: the same actions as without, and one score of each kind per observation.
    let act = format!("/v1/policies/{safedice}/act");
    let plain = ok_json(post(&app, &act, json!({"observations": observations})).await).await;
    assert!(plain.get("safety").is_none(), "{plain}");
    let scored = json!({"observations": observations, "safety_score": true});
    let answer = ok_json(post(&app, &act, scored.clone()).await).await;
    assert_eq!(answer["actions"], plain["actions"]);
    let log_ratio = floats(&answer["safety"]["non_preferred_log_ratio"]);
    let support = floats(&answer["safety"]["out_of_support"]);
    assert_eq!((log_ratio.len(), support.len()), (rows, rows));
    assert!(log_ratio.iter().chain(&support).all(|v| v.is_finite()), "{answer}");
    assert!(support.iter().all(|&s| s >= 0.0));
    assert_eq!(ok_json(post(&app, &act, scored).await).await, answer, "deterministic");

    // /v2: the outputs by parameter, then by name, JSON and binary: the same numbers.
    let metadata = ok_json(app.get(&format!("/v2/models/{safedice}")).send().await.unwrap()).await;
    let names: Vec<&str> = metadata["outputs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["actions", SAFETY_OUTPUTS[0], SAFETY_OUTPUTS[1]]);
    let infer = format!("/v2/models/{safedice}/infer");
    let body = infer_body(&observations, json!({"parameters": {"safety_score": true}}));
    let v2 = ok_json(post(&app, &infer, body).await).await;
    let outputs = v2["outputs"].as_array().unwrap();
    assert_eq!(outputs.len(), 3);
    assert_eq!(outputs[0]["data"], json!(plain["actions"].as_array().unwrap()));
    for (output, (name, want)) in
        outputs[1..].iter().zip(SAFETY_OUTPUTS.iter().zip([&log_ratio, &support]))
    {
        assert_eq!(
            (output["name"].as_str(), output["datatype"].as_str()),
            (Some(*name), Some("FP32"))
        );
        assert_eq!(output["shape"], json!([rows]));
        assert_eq!(&floats(&output["data"]), want, "{name}");
    }
    let only = infer_body(&observations, json!({"outputs": [{"name": "out_of_support"}]}));
    let v2 = ok_json(post(&app, &infer, only).await).await;
    assert_eq!(v2["outputs"].as_array().unwrap().len(), 1);
    assert_eq!(floats(&v2["outputs"][0]["data"]), support);
    let binary = infer_body(
        &observations,
        json!({"parameters":
        {"safety_score": true, "binary_data_output": true}}),
    );
    let response = post(&app, &infer, binary).await;
    assert_eq!(response.status(), StatusCode::OK);
    let length: usize =
        response.headers()["inference-header-content-length"].to_str().unwrap().parse().unwrap();
    let bytes = response.bytes().await.unwrap();
    let header: Value = serde_json::from_slice(&bytes[..length]).unwrap();
    let sizes: Vec<usize> = (0..3)
        .map(|i| header["outputs"][i]["parameters"]["binary_data_size"].as_u64().unwrap() as usize)
        .collect();
    let (_, rest) = bytes[length..].split_at(sizes[0]);
    let decode = |b: &[u8]| -> Vec<f32> {
        b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
    };
    assert_eq!(decode(&rest[..sizes[1]]), log_ratio);
    assert_eq!(decode(&rest[sizes[1]..]), support);
    let unknown = infer_body(&observations, json!({"outputs": [{"name": "safety"}]}));
    let message =
        assert_v2_error(post(&app, &infer, unknown).await, StatusCode::UNPROCESSABLE_ENTITY).await;
    assert!(message.contains("actions, non_preferred_log_ratio, out_of_support"), "{message}");

    // By model name: the same scores.
    let model = app.post("/v1/models").json(&json!({"name": "guarded"})).send().await.unwrap();
    assert_eq!(model.status(), StatusCode::CREATED);
    let version = app
        .post("/v1/models/guarded/versions")
        .json(&json!({"policy_id": safedice}))
        .send()
        .await
        .unwrap();
    assert_eq!(version.status(), StatusCode::CREATED);
    let named = post(
        &app,
        "/v1/models/guarded/act",
        json!({"observations": observations,
                                                           "safety_score": true}),
    )
    .await;
    assert_eq!(ok_json(named).await["safety"], answer["safety"]);
    // The version counts the scores it answered on this node, by bin: /act, then /v2, by name.
    let body = infer_body(&observations, json!({"parameters": {"safety_score": true}}));
    ok_json(post(&app, "/v2/models/guarded/infer", body).await).await;
    let stats = ok_json(app.get("/v2/models/guarded/stats").send().await.unwrap()).await;
    let scores = &stats["model_stats"][0]["safety_scores"];
    for (name, values) in SAFETY_OUTPUTS.iter().zip([&log_ratio, &support]) {
        let edges = floats(&scores[name]["edges"]);
        let counts: Vec<u64> = scores[name]["counts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c.as_u64().unwrap())
            .collect();
        let mut expected = vec![0; edges.len() + 1];
        for value in values {
            expected[edges.iter().filter(|&&edge| edge <= *value).count()] += 2;
        }
        assert_eq!(counts, expected, "{name}: {stats}");
    }

    // BC: no safety outputs, and a clear 422 wherever they are asked for.
    let metadata = ok_json(app.get(&format!("/v2/models/{bc}")).send().await.unwrap()).await;
    assert_eq!(metadata["outputs"].as_array().unwrap().len(), 1);
    let refused = post(
        &app,
        &format!("/v1/policies/{bc}/act"),
        json!({"observations": observations, "safety_score": true}),
    )
    .await;
    let message =
        assert_error(refused, StatusCode::UNPROCESSABLE_ENTITY, "safety_score_unavailable").await;
    assert!(message.contains("trained by bc"), "{message}");
    let infer = format!("/v2/models/{bc}/infer");
    for extra in [
        json!({"parameters": {"safety_score": true}}),
        json!({"outputs": [{"name": "non_preferred_log_ratio"}]}),
    ] {
        let refused = post(&app, &infer, infer_body(&observations, extra)).await;
        let message = assert_v2_error(refused, StatusCode::UNPROCESSABLE_ENTITY).await;
        assert!(message.contains("SafeDICE"), "{message}");
    }
    let plain = post(
        &app,
        &infer,
        infer_body(&observations, json!({"parameters": {"safety_score": false}})),
    );
    assert_eq!(ok_json(plain.await).await["outputs"].as_array().unwrap().len(), 1);
}
