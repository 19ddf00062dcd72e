//! The service's resources through the real server: a job is refused before it is queued when
//! its estimated memory is above `--max-job-memory`; /readyz reports a data directory that cannot
//! be written or whose disk is (nearly) full; a job whose checkpoint does not fit on the disk
//! goes back to the queue and finishes once there is room.
//!
//! The full-disk tests mount a small tmpfs as the data directory (a real file system that
//! really runs out of space); where mounting is not permitted (not root, no CAP_SYS_ADMIN) they
//! say so on stderr and skip, and the classification of real ENOSPC and SQLITE_FULL errors is
//! still covered by the unit tests of `src/store/storage.rs`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use crate::support::app::{assert_error, TestApp};
use crate::support::jobs::*;
use reqwest::StatusCode;
use serde_json::{json, Value};

/// A tmpfs of a given size mounted on a fresh directory; unmounted (lazily, so a straggling
/// handle cannot keep it) and removed on drop.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    /// Mounts one, or says loudly why it cannot and returns None (the caller skips).
    fn mount(test: &str, size: &str) -> Option<Tmpfs> {
        let dir = tempfile::tempdir().unwrap();
        let options = format!("size={size}");
        let mounted = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &options, "tmpfs"])
            .arg(dir.path())
            .output();
        match mounted {
            Ok(output) if output.status.success() => Some(Tmpfs { dir }),
            failed => {
                let why = match failed {
                    Ok(output) => String::from_utf8_lossy(&output.stderr).trim().replace('\n', " "),
                    Err(e) => e.to_string(),
                };
                // Straight to the process's stderr, not eprintln!: the test harness captures
                // the latter and shows it only for failing tests.
                let mut stderr = std::io::stderr().lock();
                let _ = writeln!(
                    stderr,
                    "SKIPPED {test}: cannot mount a {size} tmpfs here ({why}); needs root or \
                     CAP_SYS_ADMIN"
                );
                None
            }
        }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Grows or shrinks it in place (files stay).
    fn resize(&self, size: &str) {
        let options = format!("remount,size={size}");
        let status = Command::new("mount").args(["-o", &options]).arg(self.path()).status();
        assert!(status.unwrap().success(), "remount the tmpfs with {size}");
    }

    /// Writes zeros to `name` until the file system is full; returns the file.
    fn fill(&self, name: &str) -> PathBuf {
        let path = self.path().join(name);
        let mut file = std::fs::File::create(&path).unwrap();
        let chunk = vec![0u8; 64 << 10];
        loop {
            match file.write_all(&chunk) {
                Ok(()) => continue,
                Err(e) if e.kind() == std::io::ErrorKind::StorageFull => return path,
                Err(e) => panic!("filling the tmpfs: {e}"),
            }
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(self.dir.path()).status();
    }
}

fn safedice_job(u: &str, n: &str, config: Value) -> Value {
    json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
           "config": config})
}

#[tokio::test]
async fn a_job_estimated_above_max_job_memory_is_refused_before_it_is_queued() {
    let app = TestApp::spawn_with(|c| c.max_job_memory = 512 << 20).await;
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;

    // Batch 65536 with the default networks: SafeDICE's step buffers alone are over 3 GiB.
    let big = safedice_job(&u, &n, json!({"iterations": 100, "batch_size": 65_536}));
    let response = app.post("/v1/jobs").json(&big).send().await.unwrap();
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "job_too_large").await;
    assert!(message.contains("an estimated 3."), "names the estimate: {message}");
    assert!(message.contains("GiB"), "{message}");
    assert!(
        message.contains("limit of 512.0 MiB (536870912 bytes) (--max-job-memory)"),
        "{message}"
    );
    assert!(message.contains("batch_size"), "says what to lower: {message}");
    assert_eq!(app.count_rows("jobs").await, 0, "nothing was queued");

    // Wide networks count too, for every algorithm.
    let wide = json!({"algorithm": "bc", "unlabeled_dataset": u,
                      "config": {"batch_size": 4096, "hidden_sizes": [4096, 4096, 4096, 4096]}});
    let response = app.post("/v1/jobs").json(&wide).send().await.unwrap();
    assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "job_too_large").await;
    assert_eq!(app.count_rows("jobs").await, 0, "nothing was queued");

    // An unknown dataset is still a 404, whatever the configuration.
    let missing = safedice_job("no-such-dataset", &n, json!({"batch_size": 65_536}));
    let response = app.post("/v1/jobs").json(&missing).send().await.unwrap();
    assert_error(response, StatusCode::NOT_FOUND, "not_found").await;

    // The same job with the default batch fits and is queued.
    let fits = safedice_job(&u, &n, json!({"iterations": 100}));
    let job = create_job(&app.client, &app.base_url, fits).await;
    assert_eq!(job["config"]["batch_size"], 512);
    assert_eq!(app.count_rows("jobs").await, 1);
}

#[tokio::test]
async fn the_default_limit_admits_default_jobs_and_refuses_far_larger_ones() {
    let app = TestApp::spawn().await;
    assert_eq!(app.config.max_job_memory, 4 << 30);
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;
    let huge = safedice_job(&u, &n, json!({"batch_size": 65_536, "hidden_sizes": [1024, 1024]}));
    let response = app.post("/v1/jobs").json(&huge).send().await.unwrap();
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "job_too_large").await;
    assert!(message.contains("limit of 4.0 GiB"), "{message}");
    assert_eq!(app.count_rows("jobs").await, 0);
    create_job(&app.client, &app.base_url, safedice_job(&u, &n, json!({"iterations": 100}))).await;
}

#[tokio::test]
async fn readyz_reports_a_data_directory_that_cannot_be_written() {
    let app = TestApp::spawn().await;
    assert_eq!(app.get("/readyz").send().await.unwrap().status(), StatusCode::OK);
    // Uploads are streamed into tmp/: a file where that directory should be breaks them, and
    // readiness must say so (chmod would not do: the tests may run as root).
    let tmp = app.data_dir().join("tmp");
    std::fs::remove_dir(&tmp).unwrap();
    std::fs::write(&tmp, b"not a directory").unwrap();
    let response = app.get("/readyz").send().await.unwrap();
    let message =
        assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "storage_unwritable").await;
    assert!(message.contains("(tmp: "), "names the directory: {message}");
    assert!(!message.contains(app.data_dir().to_str().unwrap()), "no server path: {message}");
    std::fs::remove_file(&tmp).unwrap();
    std::fs::create_dir(&tmp).unwrap();
    assert_eq!(app.get("/readyz").send().await.unwrap().status(), StatusCode::OK);
}

#[tokio::test]
async fn readyz_reports_less_free_space_than_min_free_disk() {
    let app = TestApp::spawn_with(|c| c.min_free_disk = u64::MAX).await;
    let response = app.get("/readyz").send().await.unwrap();
    let message = assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "low_disk_space").await;
    assert!(
        message.contains(&format!("below the {} bytes required (--min-free-disk)", u64::MAX)),
        "{message}"
    );
    // /healthz (liveness) is not about the disk.
    assert_eq!(app.get("/healthz").send().await.unwrap().status(), StatusCode::OK);
}

#[tokio::test]
async fn readyz_reports_a_full_disk_and_recovers_when_space_is_freed() {
    let Some(disk) =
        Tmpfs::mount("readyz_reports_a_full_disk_and_recovers_when_space_is_freed", "16m")
    else {
        return;
    };
    let data_dir = disk.path().join("data");
    let mut app = TestApp::spawn_with(|c| {
        c.data_dir = data_dir.clone();
        c.min_free_disk = 1 << 20;
    })
    .await;
    assert_eq!(app.get("/readyz").send().await.unwrap().status(), StatusCode::OK);
    let filler = disk.fill("filler");
    let response = app.get("/readyz").send().await.unwrap();
    let message = assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "low_disk_space").await;
    assert!(message.contains("below the 1048576 bytes required"), "{message}");
    std::fs::remove_file(filler).unwrap();
    assert_eq!(app.get("/readyz").send().await.unwrap().status(), StatusCode::OK);
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_whose_checkpoint_does_not_fit_goes_back_to_the_queue_and_resumes_with_room() {
    let test = "a_job_whose_checkpoint_does_not_fit_goes_back_to_the_queue_and_resumes_with_room";
    let Some(disk) = Tmpfs::mount(test, "6m") else { return };
    let data_dir = disk.path().join("data");
    let mut app = TestApp::spawn_with(|c| {
        c.data_dir = data_dir.clone();
        c.min_free_disk = 1 << 20;
    })
    .await;
    if app.skip_on_postgres("checkpoints are written to the database server's disk, not this one") {
        return;
    }
    let (unlabeled, non_preferred) = grid_datasets();
    let u = upload(&app.client, &app.base_url, &unlabeled, "grid-unlabeled").await;
    let n = upload(&app.client, &app.base_url, &non_preferred, "grid-non-preferred").await;
    // Three networks of two 512-wide layers: a checkpoint (weights and Adam moments) of about
    // 10 MB, which a 6 MiB disk cannot take.
    let job = create_job(
        &app.client,
        &app.base_url,
        json!({"algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
               "config": {"iterations": 40, "seed": 0, "hidden_sizes": [512, 512], "batch_size": 32},
               "runner": {"log_every": 5, "checkpoint_every": 10}}),
    )
    .await;
    let id = job["id"].as_str().unwrap();
    // It starts, its first checkpoint fails with SQLITE_FULL, and it is queued again (never
    // failed: wait_for_job asserts that on every poll).
    let requeued = wait_for_job(&app.client, &app.base_url, id, Duration::from_secs(120), |job| {
        job["status"] == "queued" && job["started_at"].is_string()
    })
    .await;
    assert!(requeued["error"].is_null(), "{requeued}");
    // The write filled the disk as far as it went: not ready.
    let ready = app.get("/readyz").send().await.unwrap();
    assert_error(ready, StatusCode::SERVICE_UNAVAILABLE, "low_disk_space").await;

    // Room again: the paused worker sees it, claims the job again and finishes it.
    disk.resize("128m");
    let done = wait_for_status(&app.client, &app.base_url, id, "succeeded").await;
    assert_eq!(done["progress"]["step"], done["progress"]["total"]);
    assert!(done["policy_id"].is_string() && done["error"].is_null(), "{done}");
    assert_eq!(app.get("/readyz").send().await.unwrap().status(), StatusCode::OK);
    app.stop().await;
}
