//! Named models across a fleet's API nodes: alias moves and deletes followed by the other node,
//! a shadow's series added up over both, a model created again followed after the
//! notifications stop (a LISTEN cut, a PostgreSQL restart).

use std::time::{Duration, Instant};

use reqwest::StatusCode;
use serde_json::{json, Value};

use super::{db, job, support, upload_grid, Fleet};
use crate::support::jobs::{create_job, wait_for_status};

/// Serving by name across processes: a worker registers each job's policy as the next version
/// of a model (moving `production` to the first), a second API node serves the alias, and a
/// move or delete made on the first API node reaches the second (PostgreSQL notification).
#[tokio::test]
async fn an_alias_moved_on_one_api_node_is_served_by_the_other() {
    let Some(mut fleet) = Fleet::start(1).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let api = fleet.api_url.clone();
    let created = fleet.client.post(format!("{api}/v1/models")).json(&json!({"name": "pilot"}));
    assert_eq!(created.send().await.unwrap().status(), StatusCode::CREATED);
    for (seed, alias) in [(1, Some("production")), (2, None)] {
        let mut body = job(&u, &n, 200, seed);
        body["register"] = json!({"model": "pilot", "alias": alias});
        let queued = create_job(&fleet.client, &api, body).await;
        wait_for_status(&fleet.client, &api, queued["id"].as_str().unwrap(), "succeeded").await;
    }
    let other = fleet.start_api_node().await;
    let observations = json!({"observations": support::jobs::grid_observations()});
    let version_on = |url: String| {
        let (client, body) = (fleet.client.clone(), observations.clone());
        async move {
            let answer = client.post(format!("{url}/v1/models/pilot@production/act")).json(&body);
            let answer = answer.send().await.unwrap();
            let header = answer.headers().get("x-safedice-model-version");
            (answer.status(), header.map(|v| v.to_str().unwrap().to_owned()))
        }
    };
    assert_eq!(version_on(api.clone()).await, (StatusCode::OK, Some("1".into())));
    assert_eq!(version_on(other.clone()).await, (StatusCode::OK, Some("1".into())));

    let moved = fleet
        .client
        .put(format!("{api}/v1/models/pilot/aliases/production"))
        .json(&json!({"version": 2, "actor": "fleet-test"}));
    assert_eq!(moved.send().await.unwrap().status(), StatusCode::OK);
    assert_eq!(version_on(api.clone()).await, (StatusCode::OK, Some("2".into())), "at once here");
    let started = Instant::now();
    while version_on(other.clone()).await != (StatusCode::OK, Some("2".into())) {
        assert!(started.elapsed() < Duration::from_secs(10), "the other node never followed");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    eprintln!("the other API node followed the move after {:?}", started.elapsed());

    let deleted = fleet.client.delete(format!("{api}/v1/models/pilot/aliases/production"));
    assert_eq!(deleted.send().await.unwrap().status(), StatusCode::NO_CONTENT);
    let started = Instant::now();
    while version_on(other.clone()).await.0 != StatusCode::NOT_FOUND {
        assert!(started.elapsed() < Duration::from_secs(10), "the other node kept the alias");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// A shadow's series is the fleet's: a shadow set on one API node reaches the other, both
/// compare the requests they answer, and either node's read counts every request of both (each
/// node adds its counts to the same rows of the store).
#[tokio::test]
async fn a_shadows_series_adds_up_the_requests_of_every_api_node() {
    let Some(mut fleet) = Fleet::start(1).await else { return };
    let (u, n) = upload_grid(&fleet).await;
    let api = fleet.api_url.clone();
    let created = fleet.client.post(format!("{api}/v1/models")).json(&json!({"name": "pilot"}));
    assert_eq!(created.send().await.unwrap().status(), StatusCode::CREATED);
    for seed in [1, 2] {
        let mut body = job(&u, &n, 200, seed);
        body["register"] = json!({"model": "pilot"});
        let queued = create_job(&fleet.client, &api, body).await;
        wait_for_status(&fleet.client, &api, queued["id"].as_str().unwrap(), "succeeded").await;
    }
    let other = fleet.start_api_node().await;
    let shadowed = json!({"version": 1, "shadow": {"version": 2, "sample": 1.0}});
    let moved = fleet.client.put(format!("{api}/v1/models/pilot/aliases/production"));
    assert_eq!(moved.json(&shadowed).send().await.unwrap().status(), StatusCode::OK);
    let observations = json!({"observations": support::jobs::grid_observations()});
    let act_on = |url: &str| {
        let request = fleet.client.post(format!("{url}/v1/models/pilot@production/act"));
        let request = request.json(&observations).send();
        async move { assert_eq!(request.await.unwrap().status(), StatusCode::OK) }
    };
    let shadowed_requests = |url: &str| {
        let read = fleet.client.get(format!("{url}/v1/models/pilot/shadow")).send();
        async move {
            let report: Value = read.await.unwrap().json().await.unwrap();
            let series = report["series"].as_array().unwrap().clone();
            series.iter().map(|s| s["total"]["requests"].as_u64().unwrap()).sum::<u64>()
        }
    };
    // The other node shadows once it has followed the move (a notification away).
    let started = Instant::now();
    while shadowed_requests(&other).await == 0 {
        assert!(started.elapsed() < Duration::from_secs(10), "the other node never shadowed");
        act_on(&other).await;
    }
    let before = shadowed_requests(&api).await;
    for _ in 0..5 {
        act_on(&api).await;
    }
    for _ in 0..7 {
        act_on(&other).await;
    }
    // Each read stores its own node's counts first: the other node's, then this one's.
    shadowed_requests(&other).await;
    assert_eq!(
        shadowed_requests(&api).await,
        before + 12,
        "a node's shadowed requests are missing"
    );
}

/// A model deleted and created again under its name on one API node is followed by the other
/// after the notifications stop arriving: once with every `LISTEN` connection cut (the poll
/// covers the gap until the listener reconnects) and once across a PostgreSQL restart. Each
/// time the other node answers the new model's version and never the old one's within 10 s.
#[tokio::test]
async fn a_model_created_again_is_followed_after_a_listen_cut_and_a_restart() {
    let Some(cluster) = support::postgres::private_cluster() else { return };
    let mut fleet = Fleet::start_on_database(cluster.new_database().await, 1).await;
    let (u, n) = upload_grid(&fleet).await;
    let mut policies = Vec::new();
    for seed in [1, 2] {
        let queued = create_job(&fleet.client, &fleet.api_url, job(&u, &n, 200, seed)).await;
        let id = queued["id"].as_str().unwrap();
        let done = wait_for_status(&fleet.client, &fleet.api_url, id, "succeeded").await;
        policies.push(done["policy_id"].as_str().unwrap().to_owned());
    }
    let (api, client) = (fleet.api_url.clone(), fleet.client.clone());
    let observations = json!({"observations": support::jobs::grid_observations()});
    let actions_of = |url: String| {
        let request = client.post(url).json(&observations).send();
        async move {
            let response = request.await.unwrap();
            let status = response.status();
            (status, response.json::<Value>().await.unwrap()["actions"].clone())
        }
    };
    let mut expected = Vec::new();
    for policy in &policies {
        expected.push(actions_of(format!("{api}/v1/policies/{policy}/act")).await.1);
    }
    assert_ne!(expected[0], expected[1], "the two policies act differently");
    let other = fleet.start_api_node().await;
    let recreate = |policy: String| {
        let (client, api) = (client.clone(), api.clone());
        async move {
            let ok = |r: reqwest::Response| assert!(r.status().is_success(), "{}", r.status());
            let _ = client.delete(format!("{api}/v1/models/m/aliases/prod")).send().await;
            let _ = client.delete(format!("{api}/v1/models/m")).send().await;
            ok(client
                .post(format!("{api}/v1/models"))
                .json(&json!({"name": "m"}))
                .send()
                .await
                .unwrap());
            let version = json!({"policy_id": policy});
            let versions = format!("{api}/v1/models/m/versions");
            ok(client.post(&versions).json(&version).send().await.unwrap());
            ok(client
                .put(format!("{api}/v1/models/m/aliases/prod"))
                .json(&json!({"version": 1}))
                .send()
                .await
                .unwrap());
        }
    };
    let followed = |want: Value, what: &'static str| {
        let url = format!("{other}/v1/models/m@prod/act");
        let actions_of = &actions_of;
        async move {
            let started = Instant::now();
            loop {
                let (status, actions) = actions_of(url.clone()).await;
                if status == StatusCode::OK && actions == want {
                    eprintln!("{what}: the other node followed after {:?}", started.elapsed());
                    return;
                }
                assert!(started.elapsed() < Duration::from_secs(10), "{what}: {status} {actions}");
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
    };
    recreate(policies[0].clone()).await;
    followed(expected[0].clone(), "first model").await;

    // Every LISTEN connection cut, then the model made again with the other policy.
    let mut conn = db(&fleet).await;
    let cut: i64 = sqlx::query_scalar(
        "SELECT COUNT(*) FROM (SELECT pg_terminate_backend(pid) FROM pg_stat_activity \
         WHERE datname = current_database() AND query ILIKE 'LISTEN%') AS cut",
    )
    .fetch_one(&mut conn)
    .await
    .unwrap();
    assert!(cut >= 2, "both API nodes listen: {cut} LISTEN connections");
    drop(conn);
    recreate(policies[1].clone()).await;
    followed(expected[1].clone(), "after the LISTEN cut").await;

    // PostgreSQL restarted; once it answers, the model made again once more.
    cluster.stop();
    tokio::time::sleep(Duration::from_secs(2)).await;
    cluster.start_again();
    let started = Instant::now();
    while !client.get(format!("{api}/v1/models")).send().await.unwrap().status().is_success() {
        assert!(started.elapsed() < Duration::from_secs(30), "the API node never reconnected");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    recreate(policies[0].clone()).await;
    followed(expected[0].clone(), "after the restart").await;
}
