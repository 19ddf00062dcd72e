//! Named models through the real server: create, list, patch, delete with their name rules;
//! version numbers under concurrent registrations; aliases that move with their history and
//! serve by name (`/v1/models/{name}[@alias]/act`, `/v2/models/{name}[@alias]`) exactly what
//! the policy routes serve; canaries split by request key; 409s for what is in use; a job that
//! registers its policy when it succeeds.

use std::collections::BTreeSet;

use crate::support::app::{assert_error, assert_v2_error, TestApp};
use crate::support::jobs::*;
use reqwest::StatusCode;
use serde_json::{json, Value};

/// Two policies of BC jobs with different seeds (so their actions differ): (job, policy) ids.
async fn two_policies(app: &TestApp) -> [(String, String); 2] {
    let (unlabeled, _) = grid_datasets();
    let dataset = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let mut trained = Vec::new();
    for seed in [1, 2] {
        let body = json!({"algorithm": "bc", "unlabeled_dataset": dataset,
                          "config": small_config(60, seed)});
        let job = create_job(&app.client, &app.base_url, body).await;
        let id = job["id"].as_str().unwrap().to_owned();
        let done = wait_for_status(&app.client, &app.base_url, &id, "succeeded").await;
        trained.push((id, done["policy_id"].as_str().unwrap().to_owned()));
    }
    trained.try_into().unwrap()
}

async fn create_model(app: &TestApp, name: &str) -> Value {
    let response = app
        .post("/v1/models")
        .json(&json!({"name": name, "description": "pilot", "tags": ["env=grid"]}))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::CREATED);
    assert_eq!(response.headers()["location"], format!("/v1/models/{name}").as_str());
    response.json().await.unwrap()
}

async fn register(app: &TestApp, model: &str, policy: &str) -> Value {
    let response = app
        .post(&format!("/v1/models/{model}/versions"))
        .json(&json!({"policy_id": policy}))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::CREATED);
    response.json().await.unwrap()
}

async fn move_alias(app: &TestApp, model: &str, alias: &str, body: Value) -> Value {
    let response = app
        .request(reqwest::Method::PUT, &format!("/v1/models/{model}/aliases/{alias}"))
        .json(&body)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK, "move {alias}: {body}");
    response.json().await.unwrap()
}

/// `POST {path}` with the grid's observations: (actions, the version header if any).
async fn act(app: &TestApp, path: &str, key: Option<&str>) -> (Value, Option<String>) {
    let mut request = app.post(path).json(&json!({"observations": grid_observations()}));
    if let Some(key) = key {
        request = request.header("x-safedice-request-key", key);
    }
    let response = request.send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK, "{path}");
    let version =
        response.headers().get("x-safedice-model-version").map(|v| v.to_str().unwrap().to_owned());
    let body: Value = response.json().await.unwrap();
    (body["actions"].clone(), version)
}

/// A model deleted and created again under its name on one node is a new model to every node:
/// a second server on the same store (API only; on SQLite it learns of changes by polling
/// alone) that served the old model's alias answers the new model's version, and no longer the
/// alias, within a few polls (issue: it kept the old routes, its revision being higher).
#[tokio::test]
async fn a_model_deleted_and_created_again_is_followed_by_the_other_node() {
    let a = TestApp::spawn().await;
    let b = TestApp::spawn_with(|c| {
        c.data_dir = a.data_dir().to_path_buf();
        c.database_url = a.config.database_url.clone();
        c.workers = 0;
    })
    .await;
    let [(_, old), (_, new)] = two_policies(&a).await;
    create_model(&a, "m").await;
    register(&a, "m", &old).await;
    register(&a, "m", &old).await;
    for i in 0..30 {
        move_alias(&a, "m", "prod", json!({"version": 1 + i % 2})).await;
    }
    let (old_actions, _) = act(&a, &format!("/v1/policies/{old}/act"), None).await;
    let (new_actions, _) = act(&a, &format!("/v1/policies/{new}/act"), None).await;
    assert_ne!(old_actions, new_actions, "the two policies act differently");
    let (served, _) = act(&b, "/v1/models/m@prod/act", None).await;
    assert_eq!(served, old_actions, "node B serves the old model");

    let status = |r: reqwest::Response| r.status();
    assert_eq!(status(a.delete("/v1/models/m/aliases/prod").send().await.unwrap()), 204);
    assert_eq!(status(a.delete("/v1/models/m").send().await.unwrap()), 204);
    create_model(&a, "m").await;
    register(&a, "m", &new).await;

    let observations = json!({"observations": grid_observations()});
    let started = std::time::Instant::now();
    loop {
        let response = b.post("/v1/models/m/act").json(&observations).send().await.unwrap();
        let body: Value = response.json().await.unwrap();
        if body["actions"] == new_actions {
            break;
        }
        assert!(started.elapsed().as_secs() < 10, "node B still serves {body} after 10 s");
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    let response = b.post("/v1/models/m@prod/act").json(&observations).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::NOT_FOUND, "the deleted alias is gone on B too");
}

#[tokio::test]
async fn models_are_created_listed_patched_and_deleted_under_the_name_rule() {
    let app = TestApp::spawn().await;
    let created = create_model(&app, "pilot").await;
    assert_eq!(created["latest_version"], Value::Null);
    assert_eq!(created["tags"], json!(["env=grid"]));
    let response = app.post("/v1/models").json(&json!({"name": "pilot"})).send().await.unwrap();
    assert_error(response, StatusCode::CONFLICT, "model_exists").await;
    // Names are compared without case: `Pilot` would read as `pilot` and answer as another.
    for other_case in ["Pilot", "PILOT"] {
        let response =
            app.post("/v1/models").json(&json!({"name": other_case})).send().await.unwrap();
        let message = assert_error(response, StatusCode::CONFLICT, "model_exists").await;
        assert!(message.contains("a model named pilot exists already"), "{message}");
    }

    let uuid = "6f1c0d2e-0000-4000-8000-000000000000".to_owned();
    for bad in [
        String::new(),
        "a".repeat(65),
        "a/b".into(),
        "a@b".into(),
        "-lead".into(),
        "x\u{202e}y".into(),
        "p\u{0456}lot".into(), // Cyrillic і
        "caf\u{e9}".into(),
        uuid,
    ] {
        let response = app.post("/v1/models").json(&json!({"name": bad})).send().await.unwrap();
        let message =
            assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_name").await;
        assert!(message.contains("1-64 characters") || message.contains("policy id"), "{message}");
    }
    let response = app
        .post("/v1/models")
        .json(&json!({"name": "tagged", "tags": ["has space"]}))
        .send()
        .await
        .unwrap();
    assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_model").await;
    assert_eq!(app.count_rows("models").await, 1, "a refused model is not stored");
    // `latest`, in any case, always means the newest version: no alias may take it.
    for reserved in ["latest", "LATEST", "Latest"] {
        let response = app
            .request(reqwest::Method::PUT, &format!("/v1/models/pilot/aliases/{reserved}"))
            .json(&json!({"version": 1}))
            .send()
            .await
            .unwrap();
        let message =
            assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_name").await;
        assert!(message.contains("reserved"), "{message}");
    }
    // An empty or over-long page token is a bad request, not an unknown item.
    for token in [String::new(), "a".repeat(65)] {
        let response = app.get(&format!("/v1/models?page_token={token}")).send().await.unwrap();
        let message = assert_error(response, StatusCode::BAD_REQUEST, "invalid_pagination").await;
        assert!(message.starts_with("page_token must be 1 to 64 characters"), "{message}");
    }

    create_model(&app, "second").await;
    let listed = get_json(&app.client, &app.url("/v1/models?limit=1")).await;
    assert_eq!(
        (listed["total"].as_u64(), listed["items"][0]["name"].as_str()),
        (Some(2), Some("second"))
    );
    let token = listed["next_page_token"].as_str().unwrap();
    let next =
        get_json(&app.client, &app.url(&format!("/v1/models?limit=1&page_token={token}"))).await;
    assert_eq!(next["items"][0]["name"], "pilot");

    let patched: Value = app
        .request(reqwest::Method::PATCH, "/v1/models/pilot")
        .json(&json!({"description": "the grid agent"}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        (patched["description"].as_str(), &patched["tags"]),
        (Some("the grid agent"), &json!(["env=grid"]))
    );

    assert_eq!(
        app.delete("/v1/models/second").send().await.unwrap().status(),
        StatusCode::NO_CONTENT
    );
    let response = app.get("/v1/models/second").send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    let response = app.get("/v1/models/a%2Fb").send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
}

#[tokio::test]
async fn concurrent_registrations_number_versions_without_gaps_or_repeats() {
    let app = TestApp::spawn().await;
    let [(job, policy), _] = two_policies(&app).await;
    create_model(&app, "pilot").await;
    let registrations = (0..16).map(|_| register(&app, "pilot", &policy));
    let versions: Vec<u64> = futures::future::join_all(registrations)
        .await
        .iter()
        .map(|v| v["version"].as_u64().unwrap())
        .collect();
    let distinct: BTreeSet<u64> = versions.iter().copied().collect();
    assert_eq!(distinct, (1..=16).collect(), "got {versions:?}");
    let version = get_json(&app.client, &app.url("/v1/models/pilot/versions/3")).await;
    assert_eq!(
        (version["policy_id"].as_str(), version["job_id"].as_str()),
        (Some(&*policy), Some(&*job))
    );
    assert_eq!(version["source"], "api");

    // A deleted version's number is never handed out again.
    let deleted = app.delete("/v1/models/pilot/versions/16").send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);
    assert_eq!(register(&app, "pilot", &policy).await["version"], 17);
    let listed = get_json(&app.client, &app.url("/v1/models/pilot/versions?limit=2")).await;
    assert_eq!(
        (listed["total"].as_u64(), listed["items"][0]["version"].as_u64()),
        (Some(16), Some(17))
    );

    // What a version points at cannot go: the policy, its job.
    let response = app.delete(&format!("/v1/policies/{policy}")).send().await.unwrap();
    let message = assert_error(response, StatusCode::CONFLICT, "policy_in_use").await;
    assert!(message.contains("pilot version 1"), "{message}");
    let response = app.delete(&format!("/v1/jobs/{job}")).send().await.unwrap();
    let message = assert_error(response, StatusCode::CONFLICT, "policy_in_use").await;
    assert!(message.contains("pilot version"), "{message}");
    // Registering what does not exist changes nothing.
    // A policy the body names that does not exist makes the body wrong (the model exists).
    let missing = app.post("/v1/models/pilot/versions").json(&json!({"policy_id": "nope"})).send();
    let message =
        assert_error(missing.await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "unknown_policy")
            .await;
    assert!(message.contains("policy_id"), "{message}");
    let missing = app.post("/v1/models/ghost/versions").json(&json!({"policy_id": policy})).send();
    assert_error(missing.await.unwrap(), StatusCode::NOT_FOUND, "not_found").await;
    assert_eq!(app.count_rows("model_versions").await, 16);
}

#[tokio::test]
async fn aliases_move_with_their_history_and_serve_by_name_what_the_policy_routes_serve() {
    let app = TestApp::spawn().await;
    let [(_, first), (_, second)] = two_policies(&app).await;
    create_model(&app, "pilot").await;
    register(&app, "pilot", &first).await;
    register(&app, "pilot", &second).await;
    let (by_first, _) = act(&app, &format!("/v1/policies/{first}/act"), None).await;
    let (by_second, _) = act(&app, &format!("/v1/policies/{second}/act"), None).await;
    assert_ne!(by_first, by_second, "two seeds, two policies");

    let moved = move_alias(
        &app,
        "pilot",
        "production",
        json!({"version": 1, "actor": "alice", "reason": "review"}),
    )
    .await;
    assert_eq!(
        (moved["from_version"].clone(), moved["to_version"].clone()),
        (Value::Null, json!(1))
    );
    assert_eq!(
        act(&app, "/v1/models/pilot@production/act", None).await,
        (by_first.clone(), Some("1".into()))
    );
    assert_eq!(
        act(&app, "/v1/models/pilot/act", None).await,
        (by_second.clone(), Some("2".into()))
    );
    assert_eq!(
        act(&app, "/v1/models/pilot/versions/1/act", None).await,
        (by_first.clone(), Some("1".into()))
    );
    // `@LATEST` is `@latest`, the newest version; `Production` beside `production` is refused.
    assert_eq!(
        act(&app, "/v1/models/pilot@LATEST/act", None).await,
        (by_second.clone(), Some("2".into()))
    );
    let response = app
        .request(reqwest::Method::PUT, "/v1/models/pilot/aliases/Production")
        .json(&json!({"version": 2}))
        .send()
        .await
        .unwrap();
    let message = assert_error(response, StatusCode::CONFLICT, "alias_exists").await;
    assert!(message.contains("move pilot@production instead"), "{message}");

    move_alias(
        &app,
        "pilot",
        "production",
        json!({"version": 2, "actor": "bob", "expected_version": 1}),
    )
    .await;
    assert_eq!(act(&app, "/v1/models/pilot@production/act", None).await.0, by_second);
    // A mover that read the alias at version 1 does not undo bob's move.
    let stale = app
        .request(reqwest::Method::PUT, "/v1/models/pilot/aliases/production")
        .json(&json!({"version": 1, "expected_version": 1}))
        .send()
        .await
        .unwrap();
    let message = assert_error(stale, StatusCode::CONFLICT, "alias_moved").await;
    assert!(message.contains("points at version 2"), "{message}");
    move_alias(
        &app,
        "pilot",
        "production",
        json!({"version": 1, "actor": "alice", "reason": "rollback"}),
    )
    .await;
    assert_eq!(act(&app, "/v1/models/pilot@production/act", None).await.0, by_first);
    let history =
        get_json(&app.client, &app.url("/v1/models/pilot/history?alias=production")).await;
    let moves: Vec<(Value, Value, Value)> = history["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| (m["from_version"].clone(), m["to_version"].clone(), m["actor"].clone()))
        .collect();
    assert_eq!(
        moves,
        [
            (json!(2), json!(1), json!("alice")),
            (json!(1), json!(2), json!("bob")),
            (Value::Null, json!(1), json!("alice"))
        ]
    );
    assert_eq!(history["items"][0]["reason"], "rollback");

    // The Open Inference Protocol by name: the alias, a version, the model's versions.
    let v2 = json!({"inputs": [{"name": "observations", "datatype": "FP32",
                                "shape": [GRID_OBS_DIM, GRID_OBS_DIM], "data": grid_observations()}]});
    let answer: Value = app
        .post("/v2/models/pilot@production/infer")
        .json(&v2)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        (answer["model_version"].as_str(), answer["model_name"].as_str()),
        (Some("1"), Some("pilot@production"))
    );
    assert_eq!(answer["outputs"][0]["data"], by_first);
    let answer: Value = app
        .post("/v2/models/pilot/versions/2/infer")
        .json(&v2)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        (answer["model_version"].as_str(), &answer["outputs"][0]["data"]),
        (Some("2"), &by_second)
    );
    let metadata = get_json(&app.client, &app.url("/v2/models/pilot")).await;
    assert_eq!(metadata["versions"], json!(["1", "2"]));
    let stats = get_json(&app.client, &app.url("/v2/models/pilot/versions/1/stats")).await;
    assert!(stats["model_stats"][0]["inference_stats"]["success"]["count"].as_u64().unwrap() >= 3);
    for missing in [
        "/v2/models/pilot@staging/infer",
        "/v2/models/pilot/versions/9/infer",
        "/v2/models/ghost/infer",
    ] {
        assert_v2_error(app.post(missing).json(&v2).send().await.unwrap(), StatusCode::NOT_FOUND)
            .await;
    }
    for missing in
        ["/v1/models/pilot@staging/act", "/v1/models/ghost/act", "/v1/models/pilot/versions/0/act"]
    {
        let response = app.post(missing).json(&json!({"observations": grid_observations()})).send();
        assert_error(response.await.unwrap(), StatusCode::NOT_FOUND, "not_found").await;
    }

    // Bad moves are refused with the rule, and nothing is recorded.
    for (alias, body, code) in [
        ("42", json!({"version": 1}), "invalid_name"),
        ("latest", json!({"version": 1}), "invalid_name"),
        (
            "canary",
            json!({"version": 1, "canary": {"version": 2, "weight": 1.5}}),
            "invalid_canary",
        ),
    ] {
        let response = app
            .request(reqwest::Method::PUT, &format!("/v1/models/pilot/aliases/{alias}"))
            .json(&body)
            .send()
            .await
            .unwrap();
        assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, code).await;
    }
    let response = app
        .request(reqwest::Method::PUT, "/v1/models/pilot/aliases/staging")
        .json(&json!({"version": 7}))
        .send()
        .await
        .unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    assert_eq!(app.count_rows("model_alias_moves").await, 3);
    // A canary of the alias's own version splits nothing: the alias points there, no canary.
    let same = move_alias(
        &app,
        "pilot",
        "same",
        json!({"version": 1, "canary": {"version": 1, "weight": 0.5}, "actor": "alice"}),
    )
    .await;
    assert_eq!((&same["to_version"], &same["canary"]), (&json!(1), &Value::Null), "{same}");
    let deleted = app.delete("/v1/models/pilot/aliases/same?actor=alice").send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);

    // In use: the model while an alias points into it, the version an alias points at.
    let response = app.delete("/v1/models/pilot").send().await.unwrap();
    let message = assert_error(response, StatusCode::CONFLICT, "model_in_use").await;
    assert!(message.contains("production"), "{message}");
    let response = app.delete("/v1/models/pilot/versions/1").send().await.unwrap();
    assert_error(response, StatusCode::CONFLICT, "version_in_use").await;
    let deleted =
        app.delete("/v1/models/pilot/aliases/production?actor=alice").send().await.unwrap();
    assert_eq!(deleted.status(), StatusCode::NO_CONTENT);
    let response = app
        .post("/v1/models/pilot@production/act")
        .json(&json!({"observations": grid_observations()}))
        .send();
    assert_error(response.await.unwrap(), StatusCode::NOT_FOUND, "not_found").await;
    assert_eq!(
        app.delete("/v1/models/pilot").send().await.unwrap().status(),
        StatusCode::NO_CONTENT
    );
    assert_eq!(app.count_rows("policies").await, 2, "a model's delete keeps the policies");
    assert_eq!(app.count_rows("model_alias_moves").await, 0);
}

#[tokio::test]
async fn a_canary_answers_its_share_and_the_same_key_always_gets_the_same_version() {
    let app = TestApp::spawn().await;
    let [(_, first), (_, second)] = two_policies(&app).await;
    create_model(&app, "pilot").await;
    register(&app, "pilot", &first).await;
    register(&app, "pilot", &second).await;
    let canary = json!({"version": 1, "canary": {"version": 2, "weight": 0.25}});
    let version = get_json(&app.client, &app.url("/v1/models/pilot/versions/2")).await;
    assert_eq!((version["algorithm"].as_str(), &version["job_name"]), (Some("bc"), &Value::Null));
    let moved = move_alias(&app, "pilot", "production", canary.clone()).await;
    assert_eq!(moved["canary"], json!({"version": 2, "weight": 0.25}));
    let ended = move_alias(&app, "pilot", "production", json!({"version": 2})).await;
    assert_eq!(
        (ended["from_version"].as_u64(), &ended["from_canary"]),
        (Some(1), &json!({"version": 2, "weight": 0.25}))
    );
    move_alias(&app, "pilot", "production", canary.clone()).await;
    let mut canaries = 0;
    for key in 0..200 {
        let key = format!("agent-{key}");
        let (_, version) = act(&app, "/v1/models/pilot@production/act", Some(&key)).await;
        let (_, again) = act(&app, "/v1/models/pilot@production/act", Some(&key)).await;
        assert_eq!(version, again, "key {key} switched versions");
        canaries += usize::from(version.as_deref() == Some("2"));
    }
    // 200 keys at 25%: 50 expected; [25, 75] holds with overwhelming probability.
    assert!((25..=75).contains(&canaries), "{canaries} of 200 keys went to the canary");
}

#[tokio::test]
async fn a_job_registers_its_policy_as_the_next_version_when_it_succeeds() {
    let app = TestApp::spawn().await;
    let (unlabeled, _) = grid_datasets();
    let dataset = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let body = |model: &str| {
        json!({"algorithm": "bc", "unlabeled_dataset": dataset, "config": small_config(40, 3),
               "register": {"model": model, "alias": "staging"}})
    };
    let response = app.post("/v1/jobs").json(&body("ghost")).send().await.unwrap();
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_config").await;
    assert!(message.contains("register.model") && message.contains("POST /v1/models"), "{message}");
    assert_eq!(app.count_rows("jobs").await, 0);

    create_model(&app, "pilot").await;
    let job = create_job(&app.client, &app.base_url, body("pilot")).await;
    assert_eq!(job["register"], json!({"model": "pilot", "alias": "staging"}));
    let id = job["id"].as_str().unwrap();
    // While the job may still register into it, the model cannot be deleted.
    let response = app.delete("/v1/models/pilot").send().await.unwrap();
    if response.status() == StatusCode::CONFLICT {
        let message = assert_error(response, StatusCode::CONFLICT, "model_in_use").await;
        assert!(message.contains(id) || message.contains("staging"), "{message}");
    } else {
        panic!("a model a job will register into was deleted: {}", response.status());
    }
    let done = wait_for_status(&app.client, &app.base_url, id, "succeeded").await;
    let model = get_json(&app.client, &app.url("/v1/models/pilot")).await;
    assert_eq!(model["latest_version"], 1);
    assert_eq!(model["aliases"][0]["alias"], "staging");
    assert_eq!(model["aliases"][0]["version"], 1);
    let version = get_json(&app.client, &app.url("/v1/models/pilot/versions/1")).await;
    assert_eq!(version["policy_id"], done["policy_id"]);
    assert_eq!(version["source"], format!("job {id}"));
    let history = get_json(&app.client, &app.url("/v1/models/pilot/history")).await;
    assert_eq!(history["items"][0]["actor"], format!("job {id}"));
    let policy = done["policy_id"].as_str().unwrap();
    let (by_name, version) = act(&app, "/v1/models/pilot@staging/act", None).await;
    assert_eq!(version.as_deref(), Some("1"));
    assert_eq!(by_name, act(&app, &format!("/v1/policies/{policy}/act"), None).await.0);
    // The log tells of the registration once it committed, with its version.
    let log = get_json(&app.client, &app.url(&format!("/v1/jobs/{id}/logs"))).await;
    let lines: Vec<&str> =
        log.as_array().unwrap().iter().filter_map(|l| l["message"].as_str()).collect();
    assert!(
        lines.contains(
            &"registered the policy as version 1 of model pilot, alias staging moved to it"
        ),
        "{lines:?}"
    );
}

/// The documented batch limit is reachable on every action route: 16,384 observations as JSON
/// are far over the 2 MB other bodies may have; the action routes take up to 16 MiB. One row
/// more is 422 `batch_too_large`, a body over 16 MiB 413.
#[tokio::test]
async fn a_full_batch_fits_every_action_route_and_one_row_more_is_refused() {
    let app = TestApp::spawn().await;
    let [(_, policy), _] = two_policies(&app).await;
    create_model(&app, "pilot").await;
    register(&app, "pilot", &policy).await;
    let row: Vec<f64> = (0..GRID_OBS_DIM).map(|i| (i as f64 + 1.0) * 0.123_456_789_012_3).collect();
    let batch = |rows: usize| json!({"observations": vec![row.clone(); rows]});
    let full = serde_json::to_vec(&batch(16_384)).unwrap();
    assert!(full.len() > 2_000_000, "the test's body must be over the 2 MB default");
    for path in [format!("/v1/policies/{policy}/act"), "/v1/models/pilot/act".into()] {
        let response = app
            .post(&path)
            .header("content-type", "application/json")
            .body(full.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{path}");
        let body: Value = response.json().await.unwrap();
        assert_eq!(body["actions"].as_array().unwrap().len(), 16_384);
        let response = app.post(&path).json(&batch(16_385)).send().await.unwrap();
        assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "batch_too_large").await;
    }
    let v2 = json!({"inputs": [{"name": "observations", "datatype": "FP32",
                                "shape": [16_384, GRID_OBS_DIM], "data": vec![row.clone(); 16_384]}]});
    let response = app.post("/v2/models/pilot/infer").json(&v2).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let huge = vec![b' '; (16 << 20) + 1];
    let response = app
        .post("/v1/models/pilot/act")
        .header("content-type", "application/json")
        .body(huge)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::PAYLOAD_TOO_LARGE);
}

/// `/metrics`'s value of a gauge.
async fn gauge(app: &TestApp, name: &str) -> f64 {
    let text = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    let line = text.lines().find(|l| l.starts_with(&format!("{name} "))).unwrap_or_else(|| {
        panic!("no {name} in /metrics:\n{text}");
    });
    line.rsplit(' ').next().unwrap().parse().unwrap()
}

/// Named models take their policies through the policy cache: with room for one policy, six
/// models (and aliases) over two policies all answer, the cache holds one policy, and once no
/// request is in flight nothing else holds one (routing tables pin none; before, each table
/// held its own policies outside the budget).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn models_share_the_policy_cache_and_hold_no_policy_outside_its_budget() {
    let app = TestApp::spawn_with(|c| c.policy_cache_bytes = 1).await;
    let [(_, first), (_, second)] = two_policies(&app).await;
    let first_actions = act(&app, &format!("/v1/policies/{first}/act"), None).await.0;
    let second_actions = act(&app, &format!("/v1/policies/{second}/act"), None).await.0;
    for (i, policy) in [&first, &second, &first, &second, &first, &second].iter().enumerate() {
        let name = format!("shared-{i}");
        create_model(&app, &name).await;
        register(&app, &name, policy).await;
        move_alias(&app, &name, "prod", json!({"version": 1, "actor": "test"})).await;
    }
    for round in 0..2 {
        for i in 0..6 {
            let expected = if i % 2 == 0 { &first_actions } else { &second_actions };
            for path in
                [format!("/v1/models/shared-{i}/act"), format!("/v1/models/shared-{i}@prod/act")]
            {
                let (actions, version) = act(&app, &path, None).await;
                assert_eq!(
                    (&actions, version.as_deref()),
                    (expected, Some("1")),
                    "{path}, round {round}"
                );
            }
        }
    }
    assert_eq!(gauge(&app, "safedice_policies_loaded").await, 1.0);
    assert_eq!(gauge(&app, "safedice_policy_bytes_outside_cache").await, 0.0);
}
