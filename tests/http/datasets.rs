//! The dataset API end to end: uploads in every format through the real server into a real
//! SQLite file, each class of bad input with its status and code and nothing stored, the upload
//! limit, pagination, deletion (and its refusal while a job needs the data), restart.

use crate::support::app::{assert_error, TestApp};
use reqwest::StatusCode;
use safedice::data::{
    write_csv, write_jsonl, write_npz, ActionSpace, Actions, Dataset, DatasetParts,
};
use sha2::{Digest, Sha256};

/// Two episodes of a 3-d observation, 2-d action task with rewards and costs; the second ends
/// in a terminal state.
fn continuous_dataset() -> Dataset {
    let actions = vec![0.5, -0.25, 1.0, 0.0, -1.0, 0.75, 0.125, 0.5, -0.5, 0.25];
    Dataset::new(DatasetParts {
        obs_dim: 3,
        action_space: ActionSpace::infer_continuous(&actions, 2),
        observations: (0..15).map(|i| i as f32 * 0.1 - 0.7).collect(),
        actions: Actions::Continuous(actions),
        next_observations: (0..15).map(|i| i as f32 * 0.1 - 0.4).collect(),
        terminals: vec![false, false, false, false, true],
        episode_ids: vec![4, 4, 4, 9, 9],
        rewards: Some(vec![1.0, 0.5, 0.25, -1.0, 2.0]),
        costs: Some(vec![0.0, 1.0, 0.0, 0.0, 1.0]),
    })
    .unwrap()
}

/// One episode with discrete actions 0..3 and neither rewards nor costs.
fn discrete_dataset() -> Dataset {
    Dataset::new(DatasetParts {
        obs_dim: 2,
        action_space: ActionSpace::Discrete { n: 3 },
        observations: vec![0.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0],
        actions: Actions::Discrete(vec![0, 2, 1, 2]),
        next_observations: vec![1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0, 5.0],
        terminals: vec![false, false, false, true],
        episode_ids: vec![0, 0, 0, 0],
        rewards: None,
        costs: None,
    })
    .unwrap()
}

type Writer = fn(&Dataset, &std::path::Path) -> std::io::Result<()>;
const FORMATS: [(&str, Writer); 3] =
    [("jsonl", write_jsonl), ("csv", write_csv), ("npz", write_npz)];

fn file_bytes(dataset: &Dataset, extension: &str, writer: Writer) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(format!("demos.{extension}"));
    writer(dataset, &path).unwrap();
    std::fs::read(path).unwrap()
}

fn jsonl(lines: &[&str]) -> Vec<u8> {
    lines.join("\n").into_bytes()
}

#[tokio::test]
async fn every_format_round_trips_into_the_store() {
    let app = TestApp::spawn().await;
    let store = app.store().await;
    for (extension, writer) in FORMATS {
        for original in [continuous_dataset(), discrete_dataset()] {
            let bytes = file_bytes(&original, extension, writer);
            let file_name = format!("demos.{extension}");
            let response = app.upload_dataset(&file_name, bytes.clone(), Some(" walker ")).await;
            assert_eq!(response.status(), StatusCode::CREATED, "{extension}");
            let location = response.headers()["location"].to_str().unwrap().to_owned();
            let body: serde_json::Value = response.json().await.unwrap();
            let id = body["id"].as_str().unwrap();
            assert_eq!(location, format!("/v1/datasets/{id}"));
            assert_eq!(body["name"], "walker");
            assert_eq!(body["format"], extension);
            assert_eq!(body["transitions"], original.len());
            assert_eq!(body["episodes"], original.episodes());
            assert_eq!(body["obs_dim"], original.obs_dim());
            assert_eq!(
                body["action_space"],
                serde_json::to_value(original.action_space()).unwrap()
            );
            assert_eq!(body["sha256"], hex::encode(Sha256::digest(&bytes)));
            assert_eq!(body["bytes"], bytes.len());
            assert_eq!(body["stats"]["episodes"], original.episodes());
            assert_eq!(body["stats"]["episode_return"].is_object(), original.rewards().is_some());

            let fetched: serde_json::Value =
                app.get(&location).send().await.unwrap().json().await.unwrap();
            assert_eq!(fetched, body);
            let loaded = store.load_dataset(&id.to_owned().into()).await.unwrap();
            assert_eq!(loaded, original, "{extension} did not round-trip");
        }
    }
    assert_eq!(app.count_rows("datasets").await, 6);
    assert_eq!(app.stored_dataset_bytes().await, 6);
    assert!(app.files_in("tmp").is_empty());
    store.close().await;
}

#[tokio::test]
async fn the_name_defaults_to_the_file_name() {
    let app = TestApp::spawn().await;
    let bytes = file_bytes(&discrete_dataset(), "csv", write_csv);
    let response = app.upload_dataset("grid.csv", bytes, None).await;
    let body: serde_json::Value = response.json().await.unwrap();
    assert_eq!(body["name"], "grid.csv");
    assert_eq!(body["description"], serde_json::Value::Null);
}

#[tokio::test]
async fn bad_dataset_files_get_422_with_a_precise_message_and_store_nothing() {
    let app = TestApp::spawn().await;
    let npz = file_bytes(&continuous_dataset(), "npz", write_npz);
    let cases: Vec<(&str, &str, Vec<u8>, &str, &str)> = vec![
        ("empty file", "demos.jsonl", Vec::new(), "empty_dataset", ""),
        ("unknown format", "demos.txt", b"hello world\n".to_vec(), "unknown_format", ""),
        (
            "ragged observations",
            "demos.jsonl",
            jsonl(&[
                r#"{"episode": 0, "obs": [0.0, 1.0], "action": [0.5]}"#,
                r#"{"episode": 0, "obs": [0.0], "action": [0.5]}"#,
            ]),
            "invalid_dataset",
            "line 2",
        ),
        (
            "mixed discrete and continuous actions",
            "demos.jsonl",
            jsonl(&[
                r#"{"episode": 0, "obs": [0.0], "action": 1}"#,
                r#"{"episode": 0, "obs": [1.0], "action": [0.5]}"#,
            ]),
            "invalid_dataset",
            "line 2",
        ),
        (
            "non-finite value",
            "demos.csv",
            b"episode,obs_0,act_0\n0,0.5,0.1\n0,nan,0.2\n".to_vec(),
            "invalid_dataset",
            "",
        ),
        (
            "non-contiguous episodes",
            "demos.csv",
            b"episode,obs_0,act_0\n0,0.5,0.1\n1,0.5,0.2\n0,0.25,0.3\n".to_vec(),
            "invalid_dataset",
            "",
        ),
        ("truncated archive", "demos.npz", npz[..npz.len() / 2].to_vec(), "invalid_dataset", ""),
    ];
    for (what, file_name, contents, code, mentions) in cases {
        let response = app.upload_dataset(file_name, contents, None).await;
        let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, code).await;
        assert!(message.contains(mentions), "{what}: {message:?} should mention {mentions:?}");
        app.assert_no_datasets_stored().await;
    }
}

#[tokio::test]
async fn malformed_forms_get_400_or_422_and_store_nothing() {
    let app = TestApp::spawn().await;
    let valid = file_bytes(&discrete_dataset(), "jsonl", write_jsonl);
    let part = |bytes: Vec<u8>| reqwest::multipart::Part::bytes(bytes).file_name("demos.jsonl");
    let send = |form: reqwest::multipart::Form| app.post("/v1/datasets").multipart(form).send();

    let no_file = reqwest::multipart::Form::new().text("name", "walker");
    assert_error(send(no_file).await.unwrap(), StatusCode::BAD_REQUEST, "missing_file").await;
    let unknown =
        reqwest::multipart::Form::new().part("file", part(valid.clone())).text("tags", "x");
    assert_error(send(unknown).await.unwrap(), StatusCode::BAD_REQUEST, "unknown_field").await;
    let twice = reqwest::multipart::Form::new()
        .part("file", part(valid.clone()))
        .part("file", part(valid.clone()));
    assert_error(send(twice).await.unwrap(), StatusCode::BAD_REQUEST, "duplicate_field").await;
    let blank_name =
        reqwest::multipart::Form::new().part("file", part(valid.clone())).text("name", "  ");
    assert_error(send(blank_name).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_name")
        .await;
    let long_description = reqwest::multipart::Form::new()
        .part("file", part(valid.clone()))
        .text("description", "x".repeat(5000));
    let response = send(long_description).await.unwrap();
    assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_description").await;
    let bad_role =
        reqwest::multipart::Form::new().part("file", part(valid.clone())).text("role", "labeled");
    let response = send(bad_role).await.unwrap();
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_role").await;
    assert!(message.contains("`unlabeled` or `non_preferred`"), "{message}");
    let json = app.post("/v1/datasets").json(&serde_json::json!({"file": "demos.jsonl"})).send();
    assert_error(json.await.unwrap(), StatusCode::BAD_REQUEST, "not_multipart").await;
    app.assert_no_datasets_stored().await;
}

#[tokio::test]
async fn a_dataset_keeps_its_role_and_jobs_refuse_it_in_the_other_place() {
    let app = TestApp::spawn_with(|c| c.workers = 0).await;
    let valid = file_bytes(&discrete_dataset(), "jsonl", write_jsonl);
    let upload = |role: &'static str| {
        let part = reqwest::multipart::Part::bytes(valid.clone()).file_name("demos.jsonl");
        let form = reqwest::multipart::Form::new().part("file", part).text("role", role);
        app.post("/v1/datasets").multipart(form).send()
    };
    let u: serde_json::Value = upload("unlabeled").await.unwrap().json().await.unwrap();
    let n: serde_json::Value = upload("non_preferred").await.unwrap().json().await.unwrap();
    assert_eq!(
        (u["role"].as_str(), n["role"].as_str()),
        (Some("unlabeled"), Some("non_preferred"))
    );
    let listed = app.get("/v1/datasets").send().await.unwrap().text().await.unwrap();
    assert!(listed.contains(r#""role":"non_preferred""#), "{listed}");
    let swapped = serde_json::json!({"algorithm": "safedice", "unlabeled_dataset": n["id"],
                                     "non_preferred_dataset": u["id"]});
    let response = app.post("/v1/jobs").json(&swapped).send().await.unwrap();
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_config").await;
    assert!(message.contains("uploaded with role `non_preferred`") && message.contains("swapped"));
    assert_eq!(app.count_rows("jobs").await, 0);
}

#[tokio::test]
async fn uploads_over_the_limit_get_413_and_store_nothing() {
    let limit = 2048;
    let app = TestApp::spawn_with(|c| c.max_upload_bytes = limit).await;
    let line = r#"{"episode": 0, "obs": [0.0, 1.0], "action": [0.5], "next_obs": [1.0, 2.0]}"#;
    let file_of = |size: usize| {
        let mut bytes = Vec::new();
        while bytes.len() + line.len() < size {
            bytes.extend_from_slice(line.as_bytes());
            bytes.push(b'\n');
        }
        bytes.resize(size, b' ');
        bytes
    };
    // One byte over: caught while streaming.
    let response = app.upload_dataset("demos.jsonl", file_of(limit as usize + 1), None).await;
    let message = assert_error(response, StatusCode::PAYLOAD_TOO_LARGE, "payload_too_large").await;
    assert!(message.contains("2048"), "{message}");
    app.assert_no_datasets_stored().await;
    // Far over: refused from Content-Length before anything is written.
    let response = app.upload_dataset("demos.jsonl", file_of(300 * 1024), None).await;
    assert_error(response, StatusCode::PAYLOAD_TOO_LARGE, "payload_too_large").await;
    app.assert_no_datasets_stored().await;
    // Exactly at the limit: accepted.
    let response = app.upload_dataset("demos.jsonl", file_of(limit as usize), None).await;
    let body: serde_json::Value = response.json().await.unwrap();
    assert_eq!(body["bytes"], limit, "{body}");
}

async fn page(app: &TestApp, query: &str) -> serde_json::Value {
    let response = app.get(&format!("/v1/datasets{query}")).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    response.json().await.unwrap()
}

#[tokio::test]
async fn listing_pages_newest_first_and_survives_a_restart() {
    let mut app = TestApp::spawn().await;
    let csv = file_bytes(&discrete_dataset(), "csv", write_csv);
    let mut ids = Vec::new();
    for _ in 0..3 {
        ids.push(app.create_dataset("grid.csv", csv.clone()).await);
    }
    let item_ids = |page: &serde_json::Value| -> Vec<String> {
        page["items"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| d["id"].as_str().unwrap().to_owned())
            .collect()
    };
    let first = page(&app, "?limit=2").await;
    assert_eq!(item_ids(&first), vec![ids[2].clone(), ids[1].clone()]);
    assert_eq!((first["total"].as_u64(), first["next_offset"].as_u64()), (Some(3), Some(2)));
    let second = page(&app, "?limit=2&offset=2").await;
    assert_eq!(item_ids(&second), vec![ids[0].clone()]);
    assert!(second["next_offset"].is_null());
    let everything = page(&app, "").await;
    assert_eq!(everything["limit"], 50);

    let response = app.get("/v1/datasets?limit=0").send().await.unwrap();
    assert_error(response, StatusCode::BAD_REQUEST, "invalid_pagination").await;
    let response = app.get("/v1/datasets?limit=many").send().await.unwrap();
    assert_error(response, StatusCode::BAD_REQUEST, "bad_request").await;

    app.restart().await;
    assert_eq!(page(&app, "").await, everything);
    let store = app.store().await;
    for id in &ids {
        assert_eq!(store.load_dataset(&id.clone().into()).await.unwrap(), discrete_dataset());
    }
    store.close().await;
}

#[tokio::test]
async fn delete_removes_row_and_file_unless_an_active_job_needs_the_data() {
    // No workers: the job rows below are written by hand, and a worker would claim the queued
    // one (and fail it, freeing its dataset) while the test still expects it queued.
    let app = TestApp::spawn_with(|c| c.workers = 0).await;
    let jsonl = file_bytes(&continuous_dataset(), "jsonl", write_jsonl);
    let unlabeled = app.create_dataset("u.jsonl", jsonl.clone()).await;
    let non_preferred = app.create_dataset("n.jsonl", jsonl.clone()).await;
    let unused = app.create_dataset("x.jsonl", jsonl).await;
    app.insert_job("job-q", "queued", &unlabeled, None).await;
    app.insert_job("job-r", "running", "other", Some(&non_preferred)).await;
    app.insert_job("job-done", "succeeded", &unused, None).await;

    for (id, job) in [(&unlabeled, "job-q"), (&non_preferred, "job-r")] {
        let response = app.delete(&format!("/v1/datasets/{id}")).send().await.unwrap();
        let message = assert_error(response, StatusCode::CONFLICT, "dataset_in_use").await;
        assert!(message.contains(job), "{message}");
    }
    assert_eq!(app.count_rows("datasets").await, 3);

    // A finished job does not hold its data.
    let response = app.delete(&format!("/v1/datasets/{unused}")).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::NO_CONTENT);
    assert_eq!(app.count_rows("datasets").await, 2);
    assert_eq!(app.stored_dataset_bytes().await, 2);
    let response = app.get(&format!("/v1/datasets/{unused}")).send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    let response = app.delete(&format!("/v1/datasets/{unused}")).send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;

    let mut db = app.db().await;
    sqlx::query("UPDATE jobs SET status = 'cancelled' WHERE id = 'job-q'")
        .execute(&mut db)
        .await
        .unwrap();
    let response = app.delete(&format!("/v1/datasets/{unlabeled}")).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::NO_CONTENT);
    assert_eq!(app.count_rows("datasets").await, 1);
}

#[tokio::test]
async fn uploads_need_the_token_and_unknown_ids_are_404() {
    let app = TestApp::spawn_with(|c| c.api_token = Some("t0ken".into())).await;
    let bytes = file_bytes(&discrete_dataset(), "jsonl", write_jsonl);
    let form = reqwest::multipart::Form::new()
        .part("file", reqwest::multipart::Part::bytes(bytes).file_name("demos.jsonl"));
    let response = app.client.post(app.url("/v1/datasets")).multipart(form).send().await.unwrap();
    assert_error(response, StatusCode::UNAUTHORIZED, "unauthorized").await;
    app.assert_no_datasets_stored().await;
    let response = app.get("/v1/datasets/does-not-exist").send().await.unwrap();
    let message = assert_error(response, StatusCode::NOT_FOUND, "not_found").await;
    assert!(message.contains("does-not-exist"), "{message}");
}

#[tokio::test]
async fn orphaned_files_from_a_crash_are_removed_at_start_up() {
    let mut app = TestApp::spawn().await;
    if app
        .skip_on_postgres("dataset bytes are rows there, stored with their row in one transaction")
    {
        return;
    }
    let id =
        app.create_dataset("grid.csv", file_bytes(&discrete_dataset(), "csv", write_csv)).await;
    app.stop().await;
    let orphan = app.data_dir().join("datasets").join("0000-orphan.canonical");
    let partial = app.data_dir().join("datasets").join(".abc.partial");
    std::fs::write(&orphan, b"written, row never committed").unwrap();
    std::fs::write(&partial, b"half written").unwrap();
    app.restart().await;
    assert!(!orphan.exists() && !partial.exists());
    let kept = app.data_dir().join("datasets").join(format!("{id}.canonical"));
    assert!(kept.exists(), "the stored dataset's file was removed");
}

#[tokio::test]
async fn a_dataset_previews_its_first_rows_and_episodes_and_downloads_as_npz() {
    let app = TestApp::spawn().await;
    let dataset = continuous_dataset();
    let id = app.create_dataset("demos.jsonl", file_bytes(&dataset, "jsonl", write_jsonl)).await;
    let preview: serde_json::Value = app
        .get(&format!("/v1/datasets/{id}/preview?rows=4&episodes=5"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let rows = preview["transitions"].as_array().unwrap();
    assert_eq!(rows.len(), 4);
    assert_eq!(rows[3]["episode"], 1, "the fourth row starts the second episode");
    assert_eq!(rows[1]["action"], serde_json::json!([1.0, 0.0]));
    assert_eq!((rows[1]["reward"].as_f64(), rows[1]["cost"].as_f64()), (Some(0.5), Some(1.0)));
    let episodes = preview["episodes"].as_array().unwrap();
    let summary: Vec<(u64, f64, f64, bool)> = episodes
        .iter()
        .map(|e| {
            let f = |k: &str| e[k].as_f64().unwrap();
            (
                e["length"].as_u64().unwrap(),
                f("return"),
                f("cost"),
                e["terminal"].as_bool().unwrap(),
            )
        })
        .collect();
    assert_eq!(summary, [(3, 1.75, 1.0, false), (2, 1.0, 1.0, true)]);

    let download = app.get(&format!("/v1/datasets/{id}/download")).send().await.unwrap();
    assert_eq!(download.status(), StatusCode::OK);
    let disposition = download.headers()["content-disposition"].to_str().unwrap().to_owned();
    assert_eq!(disposition, format!("attachment; filename=\"dataset-{id}.npz\""));
    let bytes = download.bytes().await.unwrap().to_vec();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("back.npz");
    std::fs::write(&path, &bytes).unwrap();
    let (_, back) = safedice::data::parse_file(&path, "back.npz").unwrap();
    assert_eq!(back.observations(), dataset.observations());
    assert_eq!(back.actions(), dataset.actions());
    assert_eq!(back.costs(), dataset.costs());
    assert_eq!(back.episode_ranges(), dataset.episode_ranges());

    let too_many = app.get(&format!("/v1/datasets/{id}/preview?rows=101")).send().await.unwrap();
    assert_error(too_many, StatusCode::BAD_REQUEST, "invalid_preview").await;
    for path in ["/v1/datasets/nope/preview", "/v1/datasets/nope/download"] {
        assert_error(app.get(path).send().await.unwrap(), StatusCode::NOT_FOUND, "not_found").await;
    }
}

/// `rows` transitions of `obs_dim` distinct values each, in episodes of 1,000 steps: an NPZ of
/// about 8 · rows · obs_dim bytes, far larger than a socket's buffers at the sizes used here.
fn wide_dataset(rows: usize, obs_dim: usize) -> Dataset {
    let observations: Vec<f32> = (0..rows * obs_dim).map(|i| (i % 9973) as f32 * 1e-3).collect();
    let actions: Vec<f32> = (0..rows).map(|i| (i % 7) as f32 * 0.1 - 0.3).collect();
    Dataset::new(DatasetParts {
        obs_dim,
        action_space: ActionSpace::infer_continuous(&actions, 1),
        next_observations: observations.iter().map(|v| v + 0.5).collect(),
        observations,
        actions: Actions::Continuous(actions),
        terminals: (0..rows).map(|i| i % 1000 == 999).collect(),
        episode_ids: (0..rows).map(|i| (i / 1000) as u32).collect(),
        rewards: None,
        costs: None,
    })
    .unwrap()
}

/// Heavy reads (a dataset's preview and download, a policy's files) beyond `--max-heavy-reads`
/// get 503 `too_many_heavy_reads` with Retry-After while one is still being sent, and the slot
/// is free again once that file has gone out whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heavy_reads_beyond_the_cap_get_503_until_the_file_in_flight_is_sent() {
    let app = TestApp::spawn_with(|c| c.max_heavy_reads = 1).await;
    let dataset = wide_dataset(100_000, 48);
    let id = crate::support::jobs::upload(&app.client, &app.base_url, &dataset, "wide").await;
    // The client reads the headers only: ~38 MB stay to be sent, so the server is mid-send.
    let download = app.get(&format!("/v1/datasets/{id}/download")).send().await.unwrap();
    assert_eq!(download.status(), StatusCode::OK);
    let length: u64 = download.headers()["content-length"].to_str().unwrap().parse().unwrap();
    for path in [
        format!("/v1/datasets/{id}/preview"),
        format!("/v1/datasets/{id}/download"),
        "/v1/policies/no-such-policy/weights".to_owned(),
    ] {
        let response = app.get(&path).send().await.unwrap();
        assert_eq!(response.headers()["retry-after"], "1", "{path}");
        assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "too_many_heavy_reads").await;
    }
    // The file, whole and as the dataset writes it.
    let received = download.bytes().await.unwrap();
    assert_eq!(received.len() as u64, length);
    let dir = tempfile::tempdir().unwrap();
    write_npz(&dataset, &dir.path().join("wide.npz")).unwrap();
    assert!(received == std::fs::read(dir.path().join("wide.npz")).unwrap());
    // Sent: the slot is free (released as the server drops the finished body).
    let started = std::time::Instant::now();
    loop {
        let path = format!("/v1/datasets/{id}/preview?rows=3&episodes=40");
        let response = app.get(&path).send().await.unwrap();
        if response.status() == StatusCode::OK {
            // Read from the stored file's first rows (several PostgreSQL chunks in): the same
            // as the preview of the whole dataset.
            let preview: serde_json::Value = response.json().await.unwrap();
            // Through JSON text, as the server writes it (f32 values in their shortest form).
            let whole = serde_json::to_string(&safedice::data::preview(&dataset, 3, 40)).unwrap();
            let whole: serde_json::Value = serde_json::from_str(&whole).unwrap();
            assert_eq!(preview, whole);
            break;
        }
        assert_eq!(response.status(), StatusCode::SERVICE_UNAVAILABLE);
        assert!(started.elapsed() < std::time::Duration::from_secs(10), "the slot stayed taken");
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}

/// One client (an address; an IPv6 /64) holds at most half of the heavy-read slots: with 2, a
/// client whose download is being sent gets 503 `too_many_heavy_reads_from_address` for a
/// second heavy read, while another address is served from the other slot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_client_holds_at_most_half_of_the_heavy_read_slots() {
    let app = TestApp::spawn_with(|c| c.max_heavy_reads = 2).await;
    let dataset = wide_dataset(100_000, 48);
    let id = crate::support::jobs::upload(&app.client, &app.base_url, &dataset, "wide").await;
    let download = app.get(&format!("/v1/datasets/{id}/download")).send().await.unwrap();
    assert_eq!(download.status(), StatusCode::OK);
    let preview = format!("/v1/datasets/{id}/preview?rows=3");
    let again = app.get(&preview).send().await.unwrap();
    assert_eq!(again.headers()["retry-after"], "1");
    let message =
        assert_error(again, StatusCode::SERVICE_UNAVAILABLE, "too_many_heavy_reads_from_address")
            .await;
    assert!(message.contains("--max-heavy-reads"), "{message}");
    let metrics = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    let held = r#"safedice_request_slots_in_use{kind="heavy_read"} 1"#;
    assert!(metrics.lines().any(|line| line == held), "{metrics}");
    // Another address on the loopback network is another client.
    let other = reqwest::Client::builder()
        .local_address("127.0.0.2".parse::<std::net::IpAddr>().unwrap())
        .build()
        .unwrap();
    let served = other.get(app.url(&preview)).send().await.unwrap();
    assert_eq!(served.status(), StatusCode::OK);
    let length: u64 = download.headers()["content-length"].to_str().unwrap().parse().unwrap();
    assert_eq!(download.bytes().await.unwrap().len() as u64, length);
}

/// A download its client stops reading (a reader at a byte a second, a stalled network): after
/// --send-stall-timeout-secs without the client taking a byte the server closes the connection,
/// and the heavy-read slot it held serves others again; before that, they get 503.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_download_its_client_stops_reading_gives_its_slot_back() {
    use std::io::{Read, Write};
    let app = TestApp::spawn_with(|c| {
        c.max_heavy_reads = 1;
        c.send_stall_timeout_secs = 1;
    })
    .await;
    let dataset = wide_dataset(100_000, 48);
    let id = crate::support::jobs::upload(&app.client, &app.base_url, &dataset, "wide").await;
    // A client with a small receive window that reads the status line and then nothing.
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let mut stalled = socket.connect(app.addr).await.unwrap().into_std().unwrap();
    stalled.set_nonblocking(false).unwrap();
    stalled.set_read_timeout(Some(std::time::Duration::from_secs(60))).unwrap();
    let request = format!("GET /v1/datasets/{id}/download HTTP/1.1\r\nHost: x\r\n\r\n");
    stalled.write_all(request.as_bytes()).unwrap();
    let mut status = [0u8; 12];
    stalled.read_exact(&mut status).unwrap();
    assert_eq!(&status, b"HTTP/1.1 200");
    let busy = app.get(&format!("/v1/datasets/{id}/preview")).send().await.unwrap();
    assert_error(busy, StatusCode::SERVICE_UNAVAILABLE, "too_many_heavy_reads").await;
    // The server gives up on the stalled client: its slot serves the next download whole.
    let started = std::time::Instant::now();
    loop {
        let response = app.get(&format!("/v1/datasets/{id}/download")).send().await.unwrap();
        if response.status() == StatusCode::OK {
            let length: usize =
                response.headers()["content-length"].to_str().unwrap().parse().unwrap();
            assert_eq!(response.bytes().await.unwrap().len(), length);
            break;
        }
        assert_eq!(response.status(), StatusCode::SERVICE_UNAVAILABLE);
        assert!(started.elapsed() < std::time::Duration::from_secs(60), "the slot stayed taken");
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    // The stalled connection was closed before its file was sent: reading on ends early.
    let received = tokio::task::spawn_blocking(move || {
        let mut rest = Vec::new();
        let _ = stalled.read_to_end(&mut rest);
        rest.len()
    })
    .await
    .unwrap();
    assert!(received < 38_000_000, "the stalled client got {received} bytes: the whole file");
}
