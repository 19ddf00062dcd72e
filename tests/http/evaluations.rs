//! Evaluations through the real server: a job's `eval` block records the paper's metrics in its
//! history while it trains; `POST /v1/policies/{id}/evaluate` runs in the background and gives
//! exactly the metrics of evaluating the downloaded weights locally; bad requests get their exact
//! status and store nothing; an evaluation interrupted by a restart runs again.

use std::time::Duration;

use crate::support::app::{assert_error, TestApp};
use crate::support::jobs::*;
use rand_chacha::ChaCha8Rng;
use reqwest::StatusCode;
use safedice::algo::{Policy, PolicySpec};
use safedice::envs;
use serde_json::{json, Value};

/// A finished BC job on six-rooms that evaluated itself every 40 policy steps.
async fn trained_bc(app: &TestApp, unlabeled: &str) -> Value {
    let job = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "bc", "unlabeled_dataset": unlabeled, "config": small_config(100, 2),
               "runner": {"log_every": 20},
               "eval": {"env": "six-rooms", "every": 40, "episodes": 30, "seed": 5}}),
    )
    .await;
    assert_eq!(
        job["eval"],
        json!({"env": "six-rooms", "every": 40, "episodes": 30, "seed": 5, "deterministic": false})
    );
    let id = job["id"].as_str().unwrap();
    wait_for_job(&app.client, &app.base_url, id, Duration::from_secs(120), |j| {
        j["status"] == "succeeded"
    })
    .await
}

/// Equal up to the last bit or so: numbers cross JSON, whose parser (serde_json without
/// `float_roundtrip`) may round the last bit differently.
fn assert_same_numbers(api: &Value, local: &Value) {
    match (api, local) {
        (Value::Number(a), Value::Number(b)) => {
            let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
            assert!((a - b).abs() <= 1e-12 * a.abs().max(b.abs()), "{a} vs {b}");
        }
        (Value::Object(a), Value::Object(b)) => {
            assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
            for (key, value) in a {
                assert_same_numbers(value, &b[key]);
            }
        }
        _ => assert_eq!(api, local),
    }
}

async fn download_policy(app: &TestApp, policy_id: &str) -> Policy {
    let response = app.get(&format!("/v1/policies/{policy_id}/weights")).send().await.unwrap();
    let spec: PolicySpec =
        serde_json::from_str(response.headers()["x-safedice-policy-spec"].to_str().unwrap())
            .unwrap();
    Policy::load(&spec, &response.bytes().await.unwrap()).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_record_eval_metrics_and_evaluations_match_a_local_run() {
    let app = TestApp::spawn().await;
    let (u, _) = upload_six_rooms(&app.client, &app.base_url).await;
    let job = trained_bc(&app, &u).await;
    let job_id = job["id"].as_str().unwrap();

    // The eval block's history: after policy steps 40 and 80, and at the end (100).
    let history =
        get_json(&app.client, &app.url(&format!("/v1/jobs/{job_id}/metrics?names=eval/average_cost,eval/cvar_cost_5,eval/normalized_return"))).await;
    let steps = |name: &str| -> Vec<u64> {
        let rows = history["rows"].as_array().unwrap();
        rows.iter().filter(|r| r["name"] == name).map(|r| r["step"].as_u64().unwrap()).collect()
    };
    for name in ["eval/average_cost", "eval/cvar_cost_5", "eval/normalized_return"] {
        assert_eq!(steps(name), [40, 80, 100], "{name}");
    }

    // The last in-training evaluation is the final policy's: the same as evaluating it locally.
    let policy_id = job["policy_id"].as_str().unwrap();
    let policy = download_policy(&app, policy_id).await;
    let act = |obs: &[f32], det: bool, rng: &mut ChaCha8Rng| policy.act(obs, det, rng);
    let local = envs::evaluate("six-rooms", act, 30, 5, false).unwrap();
    let last = |name: &str| {
        history["rows"].as_array().unwrap().iter().rfind(|r| r["name"] == name).unwrap()["value"]
            .as_f64()
            .unwrap()
    };
    assert_same_numbers(&last("eval/average_cost").into(), &local.metrics.average_cost.into());
    let local_return = local.metrics.normalized_return.into();
    assert_same_numbers(&last("eval/normalized_return").into(), &local_return);
    let resource = get_json(&app.client, &app.url(&format!("/v1/policies/{policy_id}"))).await;
    let local_cvar = local.metrics.cvar_cost.k5.into();
    assert_same_numbers(&resource["final_metrics"]["eval/cvar_cost_5"], &local_cvar);

    // That last evaluation is also stored as an evaluation of the policy, marked with its step.
    let stored =
        get_json(&app.client, &app.url(&format!("/v1/evaluations?policy_id={policy_id}"))).await;
    assert_eq!(stored["total"], 1, "{stored}");
    let at_end = &stored["items"][0];
    assert_eq!(
        (&at_end["training_step"], &at_end["source"], &at_end["status"]),
        (&json!(100), &json!("builtin"), &json!("succeeded"))
    );
    assert_eq!(
        (&at_end["env"], &at_end["episodes"], &at_end["seed"]),
        (&json!("six-rooms"), &json!(30), &json!(5))
    );
    assert_same_numbers(&at_end["metrics"], &serde_json::to_value(&local.metrics).unwrap());

    // A background evaluation with other episodes and seed.
    let response = app
        .post(&format!("/v1/policies/{policy_id}/evaluate"))
        .json(&json!({"env": "six-rooms", "episodes": 200, "seed": 9}))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let location = response.headers()["location"].to_str().unwrap().to_owned();
    let queued: Value = response.json().await.unwrap();
    assert_eq!(location, format!("/v1/evaluations/{}", queued["id"].as_str().unwrap()));
    assert_eq!(queued["metrics"], Value::Null);
    assert_eq!(
        (queued["episodes"].as_u64(), queued["deterministic"].as_bool()),
        (Some(200), Some(false))
    );
    let done = wait_for_evaluation(&app.client, &app.base_url, &location).await;
    let local = envs::evaluate("six-rooms", act, 200, 9, false).unwrap();
    assert_same_numbers(&done["metrics"], &serde_json::to_value(&local.metrics).unwrap());
    assert_same_numbers(&done["reference"], &serde_json::to_value(&local.reference).unwrap());
    assert_same_numbers(&done["mean_episode_length"], &local.mean_episode_length.into());
    assert!(done["finished_at"].is_string() && done["error"].is_null());
    let metrics = &done["metrics"];
    for key in ["normalized_return", "average_cost", "cost_violation_ratio", "normalized_cost"] {
        assert!(metrics[key].is_f64(), "{key} in {metrics}");
    }
    for k in ["50", "20", "10", "5"] {
        assert!(metrics["cvar_cost"][k].is_f64(), "CVaR {k}% in {metrics}");
    }

    let metrics = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    assert!(
        metrics.lines().any(|l| l == r#"safedice_evaluations{status="succeeded"} 2"#),
        "{metrics}"
    );
    assert!(
        metrics.lines().any(|l| l == r#"safedice_evaluations{status="queued"} 0"#),
        "{metrics}"
    );
    let listed =
        get_json(&app.client, &app.url(&format!("/v1/evaluations?policy_id={policy_id}"))).await;
    assert_eq!(listed["total"], 2);
    assert_eq!(listed["items"][0]["id"], done["id"]);
    assert_eq!(listed["items"][0]["training_step"], Value::Null);
    assert_eq!(listed["items"][1]["id"], at_end["id"]);
    let none = get_json(&app.client, &app.url("/v1/evaluations?policy_id=nope")).await;
    assert_eq!(none["total"], 0);
}

/// An eval block without `every` evaluates once, after the last step: the dashboard's forms
/// send it so when "Evaluate every" is left at "at the end". On SafeDICE, whose discriminator
/// pretraining comes first, that step is the run's last (pretraining + iterations), and the job
/// says how many pretraining steps its metrics' steps include.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_eval_block_without_every_evaluates_once_at_the_end() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_six_rooms(&app.client, &app.base_url).await;
    let job = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": small_config(60, 1), "runner": {"log_every": 10},
               "eval": {"env": "six-rooms", "episodes": 20}}),
    )
    .await;
    // The block comes back as given, `every` left out: nothing invented a schedule.
    assert_eq!(
        job["eval"],
        json!({"env": "six-rooms", "episodes": 20, "seed": 0, "deterministic": false})
    );
    let total = job["progress"]["total"].as_u64().unwrap();
    let pretraining = job["pretraining_steps"].as_u64().unwrap();
    assert!(pretraining > 0, "{job}");
    assert_eq!(total, pretraining + 60);
    let id = job["id"].as_str().unwrap();
    let done = wait_for_job(&app.client, &app.base_url, id, Duration::from_secs(180), |j| {
        j["status"] == "succeeded"
    })
    .await;

    // One evaluation, after the last step, in the history and as the policy's evaluation.
    let history = get_json(
        &app.client,
        &app.url(&format!("/v1/jobs/{id}/metrics?names=eval/average_cost,eval/normalized_return")),
    )
    .await;
    let mut steps: Vec<(String, u64)> = history["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["name"].as_str().unwrap().to_owned(), r["step"].as_u64().unwrap()))
        .collect();
    steps.sort();
    assert_eq!(
        steps,
        [("eval/average_cost".to_owned(), total), ("eval/normalized_return".to_owned(), total)]
    );
    let policy_id = done["policy_id"].as_str().unwrap();
    let stored =
        get_json(&app.client, &app.url(&format!("/v1/evaluations?policy_id={policy_id}"))).await;
    assert_eq!(stored["total"], 1, "{stored}");
    assert_eq!(stored["items"][0]["training_step"], json!(total));
    assert_eq!(stored["items"][0]["episodes"], json!(20));

    // A block with `every` still refuses 0, and `null` reads as absent.
    let refused = app
        .post("/v1/jobs")
        .json(&json!({"algorithm": "bc", "unlabeled_dataset": u,
                      "eval": {"env": "six-rooms", "every": 0}}))
        .send()
        .await
        .unwrap();
    assert_error(refused, StatusCode::UNPROCESSABLE_ENTITY, "invalid_config").await;
    let null_every = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "bc", "unlabeled_dataset": u, "config": small_config(20, 1),
               "eval": {"env": "six-rooms", "every": null, "episodes": 5}}),
    )
    .await;
    assert_eq!(null_every["eval"].get("every"), None, "{null_every}");
    assert_eq!(null_every["pretraining_steps"], json!(0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_evaluations_and_eval_blocks_are_refused_and_store_nothing() {
    let app = TestApp::spawn().await;
    let (u, n) = upload_six_rooms(&app.client, &app.base_url).await;

    // Jobs: the eval block is checked before anything is queued.
    let bad_blocks = [
        (json!({"env": "walker", "every": 10}), "eval.env: unknown environment `walker`"),
        (json!({"env": "point-goal", "every": 10}), "eval.env: point-goal: observations have"),
        (json!({"env": "six-rooms", "every": 0}), "eval.every: must be between 1"),
        (json!({"env": "six-rooms", "every": 5, "episodes": 100001}), "eval.episodes: must be"),
        (json!({"env": "six-rooms", "every": 5, "sed": 1}), "eval: unknown field `sed`"),
    ];
    for (eval, expected) in bad_blocks {
        let response = app
            .post("/v1/jobs")
            .json(&json!({"algorithm": "safedice", "unlabeled_dataset": u,
                          "non_preferred_dataset": n, "eval": eval}))
            .send()
            .await
            .unwrap();
        let message =
            assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_config").await;
        assert!(message.starts_with(expected), "{message}");
    }
    assert_eq!(app.count_rows("jobs").await, 0);

    let job = trained_bc(&app, &u).await;
    let policy_id = job["policy_id"].as_str().unwrap();
    let evaluate =
        |body: Value| app.post(&format!("/v1/policies/{policy_id}/evaluate")).json(&body).send();
    let unprocessable = [
        (json!({"env": "walker"}), "invalid_evaluation", "env: unknown environment `walker`"),
        (json!({"env": "six-rooms", "episodes": 0}), "invalid_evaluation", "episodes: must be"),
        (
            json!({"env": "cartpole-slider"}),
            "invalid_evaluation",
            "env: cartpole-slider: observations have",
        ),
        (json!({"env": "six-rooms", "episode": 3}), "invalid_body", ""),
        (json!({"episodes": 3}), "invalid_body", ""),
    ];
    for (body, code, expected) in unprocessable {
        let response = evaluate(body.clone()).await.unwrap();
        let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, code).await;
        assert!(message.contains(expected), "{body}: {message}");
    }
    let response = app
        .post("/v1/policies/no-such-policy/evaluate")
        .json(&json!({"env": "six-rooms"}))
        .send()
        .await
        .unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    let response = app.get("/v1/evaluations/no-such-evaluation").send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    // Only the job's own evaluation at the end of training.
    assert_eq!(app.count_rows("evaluations").await, 1);

    // Evaluations recorded from the user's own simulator: checked field by field.
    let record =
        |body: Value| app.post(&format!("/v1/policies/{policy_id}/evaluations")).json(&body).send();
    let reference = json!({"preferred_return": 100.0, "preferred_cost": 2.0,
                           "non_preferred_return": 100.0, "non_preferred_cost": 10.0});
    let external = |returns: Value, costs: Value| json!({"env": "sim/walk", "returns": returns, "costs": costs, "reference": reference});
    let refused = [
        (external(json!([]), json!([])), "invalid_evaluation", "returns must hold 1 to 100000"),
        (external(json!([1.0, 2.0]), json!([1.0])), "invalid_evaluation", "costs must hold one"),
        (external(json!([1.0]), json!([-1.0])), "invalid_evaluation", "costs[0] must be a finite"),
        (external(json!([1.0]), json!(["x"])), "invalid_body", ""),
        (json!({"env": "sim", "returns": [1.0], "costs": [1.0]}), "invalid_body", "reference"),
        (
            json!({"env": "", "returns": [1.0], "costs": [1.0], "reference": reference}),
            "invalid_evaluation",
            "env must be",
        ),
        // Finite values whose metrics would not be finite.
        (
            external(json!([1.7e308, -1.7e308]), json!([1.0, 1.0])),
            "invalid_evaluation",
            "metrics.return_std would not be a finite number: returns",
        ),
        (
            json!({"env": "sim", "returns": [1e10], "costs": [1.0],
                   "reference": {"preferred_return": 1e-308, "preferred_cost": 2.0,
                                 "non_preferred_return": 1.0, "non_preferred_cost": 10.0}}),
            "invalid_evaluation",
            "metrics.normalized_return would not be a finite number",
        ),
    ];
    for (body, code, expected) in refused {
        let response = record(body.clone()).await.unwrap();
        let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, code).await;
        assert!(message.contains(expected), "{body}: {message}");
    }
    let response = app
        .post("/v1/policies/no-such-policy/evaluations")
        .json(&external(json!([1.0]), json!([1.0])))
        .send()
        .await
        .unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    // Only the job's own evaluation at the end of training.
    assert_eq!(app.count_rows("evaluations").await, 1);

    let response =
        record(external(json!([50.0, 70.0, 90.0, 110.0]), json!([0.0, 4.0, 7.0, 13.0]))).await;
    let response = response.unwrap();
    assert_eq!(response.status(), StatusCode::CREATED);
    let location = response.headers()["location"].to_str().unwrap().to_owned();
    let recorded: Value = response.json().await.unwrap();
    assert_eq!(location, format!("/v1/evaluations/{}", recorded["id"].as_str().unwrap()));
    assert_eq!(
        (&recorded["status"], &recorded["source"], &recorded["env"], &recorded["episodes"]),
        (&json!("succeeded"), &json!("external"), &json!("sim/walk"), &json!(4))
    );
    let m = &recorded["metrics"];
    // By hand: 100 * 80 / 100; mean cost 6; kappa = (2 + 10) / 2; two of four above it; the
    // worst episode's cost.
    assert_eq!(
        (&m["normalized_return"], &m["average_cost"], &m["cost_threshold"]),
        (&json!(80.0), &json!(6.0), &json!(6.0))
    );
    assert_eq!((&m["cost_violation_ratio"], &m["cvar_cost"]["10"]), (&json!(0.5), &json!(13.0)));
    let listed = app.url(&format!("/v1/evaluations?policy_id={policy_id}"));
    // Newest first: the recorded one, then the job's own at the end of training.
    let items = get_json(&app.client, &listed).await["items"].clone();
    assert_eq!(items.as_array().map(Vec::len), Some(2));
    assert_eq!(items[0], recorded);
    assert!(items[1]["training_step"].is_u64(), "{items}");

    // Returns 1e200 apart: metrics that a plain sum of squares would overflow, stored finite.
    let huge = record(external(json!([1e200, -1e200]), json!([0.0, 1.0]))).await.unwrap();
    assert_eq!(huge.status(), StatusCode::CREATED);
    let huge: Value = huge.json().await.unwrap();
    let std = huge["metrics"]["return_std"].as_f64().unwrap();
    assert!((std / (2f64.sqrt() * 1e200) - 1.0).abs() < 1e-12, "{huge}");
    // A report stored unreadable (as an older version wrote overflowing metrics: null) reads
    // without its metrics and says why; every list it is in still answers.
    let mut db = app.db().await;
    sqlx::query("UPDATE evaluations SET report = $1 WHERE id = $2")
        .bind(r#"{"env":"sim/walk","metrics":{"return_std":null}}"#)
        .bind(huge["id"].as_str().unwrap())
        .execute(&mut db)
        .await
        .unwrap();
    for path in [listed.clone(), app.url("/v1/evaluations")] {
        let response = app.client.get(&path).send().await.unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{path}");
        let items: Value = response.json().await.unwrap();
        let unreadable = &items["items"][0];
        assert_eq!(unreadable["id"], huge["id"]);
        assert!(unreadable["error"].as_str().unwrap().starts_with("the stored report cannot"));
        assert_eq!(unreadable["metrics"], Value::Null, "{unreadable}");
    }
    let one = app.get(&format!("/v1/evaluations/{}", huge["id"].as_str().unwrap()));
    assert_eq!(one.send().await.unwrap().status(), StatusCode::OK);
}

/// Recording or queueing an evaluation while the policy's job is deleted: each race ends with
/// the evaluation stored and the delete refused or done after it, or the policy gone and the
/// evaluation refused with 404 — never a 500 from the database's foreign key.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn evaluations_racing_the_delete_of_their_policy_are_stored_or_refused_whole() {
    let app = TestApp::spawn().await;
    let (u, _) = upload_six_rooms(&app.client, &app.base_url).await;
    let mut jobs = Vec::new();
    for seed in 0..8 {
        let body = json!({"algorithm": "bc", "unlabeled_dataset": u,
                          "config": small_config(20, seed)});
        jobs.push(create_job(&app.client, &app.base_url, body).await);
    }
    let reference = json!({"preferred_return": 1.0, "preferred_cost": 1.0,
                           "non_preferred_return": 1.0, "non_preferred_cost": 2.0});
    let mut outcomes = Vec::new();
    for (index, job) in jobs.iter().enumerate() {
        let id = job["id"].as_str().unwrap();
        let done = wait_for_job(&app.client, &app.base_url, id, Duration::from_secs(120), |j| {
            j["status"] == "succeeded"
        });
        let policy = done.await["policy_id"].as_str().unwrap().to_owned();
        let (path, body) = if index % 2 == 0 {
            let body =
                json!({"env": "sim", "returns": [1.0], "costs": [1.0], "reference": reference});
            (format!("/v1/policies/{policy}/evaluations"), body)
        } else {
            (format!("/v1/policies/{policy}/evaluate"), json!({"env": "six-rooms", "episodes": 5}))
        };
        let evaluate = app.post(&path).json(&body).send();
        let delete = app.delete(&format!("/v1/jobs/{id}")).send();
        let (evaluated, deleted) = tokio::join!(evaluate, delete);
        let (evaluated, deleted) = (evaluated.unwrap().status(), deleted.unwrap().status());
        let stored = app.count_where("evaluations", "policy_id", &policy).await;
        outcomes.push((evaluated.as_u16(), deleted.as_u16(), stored));
    }
    eprintln!("(evaluate, delete, evaluations left) per race: {outcomes:?}");
    for (index, &(evaluated, deleted, stored)) in outcomes.iter().enumerate() {
        let ok = if index % 2 == 0 {
            // Recorded then deleted with the policy, or refused once the policy was gone.
            matches!((evaluated, deleted, stored), (201, 204, 0) | (404, 204, 0))
        } else {
            // Queued first: the delete refuses while it is queued or running (409), or comes
            // after it finished (it goes with the policy); or the policy went first.
            matches!((evaluated, deleted, stored), (202, 409, 1) | (202, 204, 0) | (404, 204, 0))
        };
        assert!(ok, "race {index}: {outcomes:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_evaluation_left_running_by_a_dead_process_runs_again_at_start() {
    let mut app = TestApp::spawn().await;
    let (u, _) = upload_six_rooms(&app.client, &app.base_url).await;
    let job = trained_bc(&app, &u).await;
    let policy_id = job["policy_id"].as_str().unwrap();
    app.stop().await;
    let mut db = app.db().await;
    sqlx::query(
        "INSERT INTO evaluations (id, policy_id, env, episodes, seed, deterministic, status, \
         created_at, started_at) VALUES ('e1', $1, 'six-rooms', 50, 1, 1, 'running', \
         '2026-01-01T00:00:00Z', '2026-01-01T00:00:01Z')",
    )
    .bind(policy_id)
    .execute(&mut db)
    .await
    .unwrap();
    drop(db);
    app.restart().await;
    let done = wait_for_evaluation(&app.client, &app.base_url, "/v1/evaluations/e1").await;
    let policy = download_policy(&app, policy_id).await;
    let act = |obs: &[f32], det: bool, rng: &mut ChaCha8Rng| policy.act(obs, det, rng);
    let local = envs::evaluate("six-rooms", act, 50, 1, true).unwrap();
    assert_same_numbers(&done["metrics"], &serde_json::to_value(&local.metrics).unwrap());
}

/// Seeds are int64 in the API's description: one above 2^63 - 1 is refused where the API takes
/// a seed, with the reason, and nothing is queued.
#[tokio::test]
async fn a_seed_above_the_largest_int64_is_refused_everywhere_a_seed_is_taken() {
    let app = TestApp::spawn().await;
    let (unlabeled, _) = upload_six_rooms(&app.client, &app.base_url).await;
    let job = trained_bc(&app, &unlabeled).await;
    let policy = job["policy_id"].as_str().unwrap();
    let too_big = 1u64 << 63;
    let evaluate = json!({"env": "six-rooms", "episodes": 5, "seed": too_big});
    let response = app.post(&format!("/v1/policies/{policy}/evaluate")).json(&evaluate).send();
    let message =
        assert_error(response.await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_body")
            .await;
    assert!(message.contains("int64"), "{message}");
    let act = json!({"observations": [vec![0.0; 66]], "deterministic": false, "seed": too_big});
    let response = app.post(&format!("/v1/policies/{policy}/act")).json(&act).send();
    let message =
        assert_error(response.await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_body")
            .await;
    assert!(message.contains("int64"), "{message}");
    // Only the job's own evaluation at the end of training.
    assert_eq!(app.count_rows("evaluations").await, 1);
    let largest = json!({"env": "six-rooms", "episodes": 5, "seed": too_big - 1});
    let response = app.post(&format!("/v1/policies/{policy}/evaluate")).json(&largest).send();
    assert_eq!(response.await.unwrap().status(), StatusCode::ACCEPTED);
}
