//! Fleet benchmark: the service as API nodes and worker processes on one database, PostgreSQL
//! (a throwaway cluster, as the tests start it) against SQLite (one data directory shared by the
//! processes of one machine). Prints a markdown report; `--out` also writes it to a file.
//!
//! ```text
//! cargo build --release --bin safedice --example fleet_bench
//! target/release/examples/fleet_bench [--jobs 16] [--workers 1,2,4] [--dataset-mb 500] \
//!     [--bin target/release/safedice] [--out bench/fleet.md]
//! ```
//!
//! 1. **Throughput**: `--jobs` short SafeDICE jobs (six-rooms data, 64-64 networks, 400
//!    iterations) queued at once on an API node (`serve --workers 0`) with 1, 2 and 4 `safedice
//!    worker` processes: jobs per hour from the first submit to the last success.
//! 2. **Claims under contention**: 8 claimers in one process, each claiming the next job and
//!    finishing it at once, over 400 queued jobs: claim latency percentiles.
//! 3. **`/act` from two API nodes** sharing the database, loaded at once by `wrk` (Debian's
//!    package; skipped without it).
//! 4. **A large dataset through the store**: upload an NPZ of about `--dataset-mb` MB through the
//!    API (stream, hash, parse, store) and load it as a worker does (read, SHA-256 check,
//!    decode).
//!
//! Needs PostgreSQL's server binaries (Debian's `postgresql`) for the PostgreSQL half.

#[path = "../tests/support/postgres.rs"]
#[allow(dead_code)]
mod postgres;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context};
use safedice::algo::{Algorithm, Preset, ResolvedConfig};
use safedice::data::{self, ActionSpace, Actions, Dataset, DatasetParts, Format};
use safedice::domain::NewJob;
use safedice::domain::{JobId, JobStatus, RunnerOptions};
use safedice::store::{NewDataset, Store};
use serde_json::{json, Value};

struct Args {
    jobs: usize,
    workers: Vec<usize>,
    dataset_mb: usize,
    bin: String,
    out: Option<PathBuf>,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = Args {
        jobs: 16,
        workers: vec![1, 2, 4],
        dataset_mb: 500,
        bin: "target/release/safedice".into(),
        out: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--jobs" => args.jobs = value()?.parse()?,
            "--workers" => {
                args.workers = value()?.split(',').map(str::parse).collect::<Result<_, _>>()?
            }
            "--dataset-mb" => args.dataset_mb = value()?.parse()?,
            "--bin" => args.bin = value()?,
            "--out" => args.out = Some(value()?.into()),
            other => bail!("unknown argument {other}"),
        }
    }
    Ok(args)
}

/// Where a fleet keeps its state.
struct Database {
    /// None: SQLite in the shared data directory.
    url: Option<String>,
}

impl Database {
    async fn fresh(name: &'static str) -> anyhow::Result<Database> {
        let url = match name {
            "sqlite" => None,
            _ => {
                let cluster = postgres::cluster().context("PostgreSQL is not installed")?;
                Some(cluster.new_database().await)
            }
        };
        Ok(Database { url })
    }

    fn args(&self) -> Vec<String> {
        self.url.iter().flat_map(|url| ["--database-url".to_owned(), url.clone()]).collect()
    }
}

/// A child process of the binary, killed when dropped.
struct Process(Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn spawn(bin: &str, args: &[String]) -> anyhow::Result<Process> {
    let child = Command::new(bin)
        .args(args)
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .spawn()
        .with_context(|| format!("cannot start {bin}"))?;
    Ok(Process(child))
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// An API node; its URL.
async fn start_api(
    bin: &str,
    db: &Database,
    data_dir: &Path,
    workers: usize,
) -> anyhow::Result<(Process, String)> {
    let port = free_port();
    let mut args: Vec<String> =
        ["serve", "--workers", &workers.to_string()].iter().map(|s| s.to_string()).collect();
    args.extend(["--bind".into(), format!("127.0.0.1:{port}"), "--data-dir".into()]);
    args.push(data_dir.display().to_string());
    args.extend(db.args());
    let process = spawn(bin, &args)?;
    let url = format!("http://127.0.0.1:{port}");
    let started = Instant::now();
    while !reqwest::get(format!("{url}/readyz")).await.is_ok_and(|r| r.status().is_success()) {
        ensure!(started.elapsed() < Duration::from_secs(60), "the API node did not come up");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    Ok((process, url))
}

fn start_worker(bin: &str, db: &Database, data_dir: &Path) -> anyhow::Result<Process> {
    let mut args = vec!["worker".to_owned(), "--data-dir".into(), data_dir.display().to_string()];
    args.extend(db.args());
    spawn(bin, &args)
}

async fn upload(client: &reqwest::Client, url: &str, path: &Path) -> anyhow::Result<String> {
    let file = tokio::fs::File::open(path).await?;
    let length = file.metadata().await?.len();
    let stream = tokio_util::io::ReaderStream::new(file);
    let part =
        reqwest::multipart::Part::stream_with_length(reqwest::Body::wrap_stream(stream), length)
            .file_name(path.file_name().unwrap().to_string_lossy().into_owned());
    let form = reqwest::multipart::Form::new().part("file", part);
    let response = client.post(format!("{url}/v1/datasets")).multipart(form).send().await?;
    ensure!(response.status() == 201, "upload failed: {}", response.text().await?);
    let body: Value = response.json().await?;
    Ok(body["id"].as_str().context("dataset id")?.to_owned())
}

/// The six-rooms unlabeled and labeled sets as NPZ files in `dir`.
fn six_rooms(dir: &Path) -> anyhow::Result<(PathBuf, PathBuf)> {
    let spec = safedice::envs::DatagenSpec {
        env: "six-rooms".into(),
        preferred: 40,
        non_preferred: 60,
        labeled: 20,
        seed: 0,
    };
    let generated = safedice::envs::generate(&spec)?;
    let (u, n) = (dir.join("unlabeled.npz"), dir.join("labeled.npz"));
    data::write_npz(&generated.unlabeled, &u)?;
    data::write_npz(generated.labeled_non_preferred.as_ref().context("labeled set")?, &n)?;
    Ok((u, n))
}

fn short_job(u: &str, n: &str, seed: usize) -> Value {
    json!({
        "algorithm": "safedice", "unlabeled_dataset": u, "non_preferred_dataset": n,
        "config": {"iterations": 400, "discriminator_iterations": 200, "hidden_sizes": [64, 64],
                   "batch_size": 256, "seed": seed},
        "runner": {"log_every": 50, "checkpoint_every": 200},
    })
}

async fn wait_until_done(
    client: &reqwest::Client,
    url: &str,
    ids: &[String],
) -> anyhow::Result<()> {
    for id in ids {
        loop {
            let job: Value = client.get(format!("{url}/v1/jobs/{id}")).send().await?.json().await?;
            match job["status"].as_str() {
                Some("succeeded") => break,
                Some("failed" | "cancelled") => bail!("job {id} ended {}", job),
                _ => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    }
    Ok(())
}

/// Jobs per hour with `workers` worker processes.
async fn throughput(args: &Args, db_name: &'static str, workers: usize) -> anyhow::Result<f64> {
    let db = Database::fresh(db_name).await?;
    let dir = tempfile::tempdir()?;
    let shared = dir.path().join("data");
    let (_api, url) = start_api(&args.bin, &db, &shared, 0).await?;
    let client = reqwest::Client::new();
    let (u_path, n_path) = six_rooms(dir.path())?;
    let (u, n) = (upload(&client, &url, &u_path).await?, upload(&client, &url, &n_path).await?);
    let mut processes = Vec::new();
    for index in 0..workers {
        // SQLite: the processes of one machine share the data directory; PostgreSQL: each has
        // its own, nothing shared but the database.
        let data_dir =
            if db.url.is_some() { dir.path().join(format!("w{index}")) } else { shared.clone() };
        processes.push(start_worker(&args.bin, &db, &data_dir)?);
    }
    // Let the workers connect and go idle before the clock starts.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let started = Instant::now();
    let mut ids = Vec::new();
    for seed in 0..args.jobs {
        let response =
            client.post(format!("{url}/v1/jobs")).json(&short_job(&u, &n, seed)).send().await?;
        let job: Value = response.json().await?;
        ids.push(job["id"].as_str().context("job id")?.to_owned());
    }
    wait_until_done(&client, &url, &ids).await?;
    Ok(args.jobs as f64 / started.elapsed().as_secs_f64() * 3600.0)
}

/// Claim latencies (seconds, sorted) of `claimers` concurrent claimers over `jobs` jobs.
async fn claim_latencies(
    db_name: &'static str,
    jobs: usize,
    claimers: usize,
) -> anyhow::Result<(Vec<f64>, f64)> {
    let db = Database::fresh(db_name).await?;
    let dir = tempfile::tempdir()?;
    let store = Store::connect(dir.path(), db.url.as_deref()).await?;
    let spec = safedice::envs::DatagenSpec {
        env: "six-rooms".into(),
        preferred: 1,
        non_preferred: 1,
        labeled: 0,
        seed: 0,
    };
    let dataset = safedice::envs::generate(&spec)?.unlabeled;
    let new = NewDataset::describe(&dataset, Format::Npz, "d".into(), None, "0".into(), 1);
    let record = store.create_dataset(new, data::encode_canonical(&dataset)).await?;
    for _ in 0..jobs {
        let job = NewJob {
            id: JobId::generate(),
            unlabeled_dataset: record.id.clone(),
            non_preferred_dataset: None,
            config: ResolvedConfig::preset(Algorithm::Bc, Preset::Service),
            runner: RunnerOptions::default(),
            eval: None,
            labels: Default::default(),
            max_attempts: 3,
            register: None,
        };
        store.insert_job(&job).await?;
    }
    let store = Arc::new(store);
    let started = Instant::now();
    let tasks: Vec<_> = (0..claimers)
        .map(|index| {
            let store = store.clone();
            tokio::spawn(async move {
                let mut latencies = Vec::new();
                let worker = format!("claimer-{index}");
                loop {
                    let t = Instant::now();
                    let claimed = store.claim_next_job(&worker, Duration::from_secs(30)).await?;
                    latencies.push(t.elapsed().as_secs_f64());
                    let Some((_, lease)) = claimed else { return anyhow::Ok(latencies) };
                    store.finish_job(&lease, JobStatus::Cancelled, None, &[]).await?;
                }
            })
        })
        .collect();
    let mut all = Vec::new();
    for task in tasks {
        all.extend(task.await??);
    }
    let elapsed = started.elapsed().as_secs_f64();
    all.sort_by(f64::total_cmp);
    store.close().await;
    Ok((all, jobs as f64 / elapsed))
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// `wrk` on both API nodes at once; (total req/s, p99 ms of each).
async fn act_two_nodes(bin: &str) -> anyhow::Result<String> {
    if Command::new("wrk").arg("--version").output().is_err() {
        return Ok("skipped: wrk is not installed (Debian package `wrk`)".into());
    }
    let db = Database::fresh("postgres").await?;
    let dir = tempfile::tempdir()?;
    let (_a, a) = start_api(bin, &db, &dir.path().join("a"), 1).await?;
    let (_b, b) = start_api(bin, &db, &dir.path().join("b"), 0).await?;
    let client = reqwest::Client::new();
    let (u_path, n_path) = six_rooms(dir.path())?;
    let (u, n) = (upload(&client, &a, &u_path).await?, upload(&client, &a, &n_path).await?);
    let job: Value = client
        .post(format!("{a}/v1/jobs"))
        .json(&short_job(&u, &n, 0))
        .send()
        .await?
        .json()
        .await?;
    let id = job["id"].as_str().context("job id")?.to_owned();
    wait_until_done(&client, &a, std::slice::from_ref(&id)).await?;
    let job: Value = client.get(format!("{a}/v1/jobs/{id}")).send().await?.json().await?;
    let policy = job["policy_id"].as_str().context("policy")?.to_owned();
    let meta: Value = client.get(format!("{a}/v1/policies/{policy}")).send().await?.json().await?;
    let obs_dim = meta["obs_dim"].as_u64().context("obs_dim")? as usize;
    let body = json!({"observations": [vec![0.5; obs_dim]]}).to_string();
    let script = dir.path().join("act.lua");
    std::fs::write(
        &script,
        format!(
            "wrk.method = \"POST\"\nwrk.body = '{body}'\nwrk.headers[\"Content-Type\"] = \"application/json\"\n"
        ),
    )?;
    let run = |url: String| {
        let script = script.clone();
        let policy = policy.clone();
        std::thread::spawn(move || {
            Command::new("wrk")
                .args(["-t1", "-c16", "-d10s", "--latency", "-s"])
                .arg(&script)
                .arg(format!("{url}/v1/policies/{policy}/act"))
                .output()
        })
    };
    // Warm both nodes' policy caches first.
    for url in [&a, &b] {
        client
            .post(format!("{url}/v1/policies/{policy}/act"))
            .body(body.clone())
            .header("content-type", "application/json")
            .send()
            .await?;
    }
    let (ra, rb) = (run(a.clone()), run(b.clone()));
    let outputs = [ra.join().expect("wrk thread")?, rb.join().expect("wrk thread")?];
    let mut total = 0.0;
    let mut lines = Vec::new();
    for (name, output) in ["node A (trains)", "node B (API only)"].iter().zip(&outputs) {
        let text = String::from_utf8_lossy(&output.stdout);
        let rps: f64 = text
            .lines()
            .find_map(|l| l.strip_prefix("Requests/sec:"))
            .context("wrk printed no Requests/sec")?
            .trim()
            .parse()?;
        let p99 = text
            .lines()
            .find(|l| l.trim_start().starts_with("99%"))
            .unwrap_or("")
            .trim()
            .to_owned();
        let errors = text.lines().find(|l| l.contains("Non-2xx") || l.contains("Socket errors"));
        total += rps;
        lines.push(format!(
            "{name}: {rps:.0} req/s, latency {p99}{}",
            errors.map(|e| format!(" ({})", e.trim())).unwrap_or_default()
        ));
    }
    lines.push(format!(
        "both nodes together: {total:.0} req/s (wrk -t1 -c16 -d10s on each, at once)"
    ));
    Ok(lines.join("\n"))
}

/// A continuous dataset of about `mb` MB as NPZ (17-dim observations, 6-dim actions, rewards
/// and costs, episodes of 1000 steps).
fn large_dataset(path: &Path, mb: usize) -> anyhow::Result<u64> {
    use rand::{Rng, SeedableRng};
    const OBS: usize = 17;
    const ACT: usize = 6;
    // Bytes per transition in the NPZ: two observations, the action, reward, cost, terminal,
    // episode id.
    let per_transition = (2 * OBS + ACT + 2) * 4 + 1 + 4;
    let n = mb * 1_000_000 / per_transition;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut floats =
        |len: usize| (0..len).map(|_| rng.random_range(-1.0f32..1.0)).collect::<Vec<_>>();
    let dataset = Dataset::new(DatasetParts {
        obs_dim: OBS,
        action_space: ActionSpace::Continuous {
            dim: ACT,
            low: vec![-1.0; ACT],
            high: vec![1.0; ACT],
        },
        observations: floats(n * OBS),
        actions: Actions::Continuous(floats(n * ACT)),
        next_observations: floats(n * OBS),
        terminals: (0..n).map(|i| i % 1000 == 999).collect(),
        episode_ids: (0..n).map(|i| (i / 1000) as u32).collect(),
        rewards: Some(floats(n)),
        costs: Some(floats(n)),
    })?;
    data::write_npz(&dataset, path)?;
    Ok(std::fs::metadata(path)?.len())
}

/// Upload through the API and load as a worker does: (upload MB/s, load MB/s, canonical MB).
async fn dataset_round_trip(
    args: &Args,
    db_name: &'static str,
    npz: &Path,
    bytes: u64,
) -> anyhow::Result<String> {
    let db = Database::fresh(db_name).await?;
    let dir = tempfile::tempdir()?;
    let (_api, url) = start_api(&args.bin, &db, dir.path(), 0).await?;
    let client = reqwest::Client::builder().timeout(Duration::from_secs(1800)).build()?;
    let started = Instant::now();
    let id = upload(&client, &url, npz).await?;
    let upload_s = started.elapsed().as_secs_f64();
    // A worker's view: on SQLite the shared data directory, on PostgreSQL a directory of its own.
    let reader_dir = match db.url {
        Some(_) => dir.path().join("reader"),
        None => dir.path().to_path_buf(),
    };
    let store = Store::connect(&reader_dir, db.url.as_deref()).await?;
    let started = Instant::now();
    let loaded = store.load_dataset(&id.clone().into()).await?;
    let load_s = started.elapsed().as_secs_f64();
    let canonical = data::encode_canonical(&loaded).len() as f64 / 1e6;
    store.close().await;
    let mb = bytes as f64 / 1e6;
    Ok(format!(
        "| {db_name} | {mb:.0} MB NPZ ({} transitions) | {upload_s:.1} s ({:.0} MB/s) | {load_s:.1} s ({:.0} MB/s of {canonical:.0} MB canonical) |",
        loaded.len(),
        mb / upload_s,
        canonical / load_s
    ))
}

/// The CPU's name, family and model (machines here differ: the same name covers Zen 4 and 5).
fn cpu_model() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |key: &str| {
        info.lines()
            .filter_map(|line| line.split_once(':'))
            .find(|(k, _)| k.trim() == key)
            .map_or_else(|| "?".to_owned(), |(_, v)| v.trim().to_owned())
    };
    format!("{}, family {} model {}", field("model name"), field("cpu family"), field("model"))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = parse_args()?;
    let mut report = vec![
        "# Fleet benchmark".to_owned(),
        String::new(),
        format!(
            "Command: `{}`. CPU: {} ({} cores). Date: {}.",
            std::env::args().collect::<Vec<_>>().join(" "),
            cpu_model(),
            std::thread::available_parallelism().map_or(0, |n| n.get()),
            chrono::Utc::now().format("%Y-%m-%d")
        ),
        String::new(),
        format!("## Jobs per hour ({} short SafeDICE jobs, queued at once)", args.jobs),
        String::new(),
        "| workers | SQLite (one shared data dir) | PostgreSQL |".into(),
        "|---|---|---|".into(),
    ];
    for &workers in &args.workers {
        let sqlite = throughput(&args, "sqlite", workers).await?;
        let postgres = throughput(&args, "postgres", workers).await?;
        eprintln!("{workers} workers: sqlite {sqlite:.0}/h, postgres {postgres:.0}/h");
        report.push(format!("| {workers} | {sqlite:.0} | {postgres:.0} |"));
    }
    report.extend([
        String::new(),
        "## Claim latency (8 concurrent claimers, 400 jobs; claim then finish)".into(),
        String::new(),
    ]);
    report.push("| database | p50 | p99 | max | claims/s |".into());
    report.push("|---|---|---|---|---|".into());
    for db in ["sqlite", "postgres"] {
        let (latencies, rate) = claim_latencies(db, 400, 8).await?;
        let ms = |p: f64| percentile(&latencies, p) * 1000.0;
        report.push(format!(
            "| {db} | {:.2} ms | {:.2} ms | {:.2} ms | {rate:.0} |",
            ms(0.5),
            ms(0.99),
            ms(1.0)
        ));
    }
    report.extend([
        String::new(),
        "## `/act` from two API nodes on one PostgreSQL".into(),
        String::new(),
        "```text".into(),
    ]);
    report.push(act_two_nodes(&args.bin).await?);
    report.push("```".into());
    report.extend([
        String::new(),
        format!("## A {} MB dataset through the store", args.dataset_mb),
        String::new(),
    ]);
    report.push("| database | dataset | upload through the API | load as a worker does |".into());
    report.push("|---|---|---|---|".into());
    let dir = tempfile::tempdir()?;
    let npz = dir.path().join("large.npz");
    let bytes = large_dataset(&npz, args.dataset_mb)?;
    for db in ["sqlite", "postgres"] {
        report.push(dataset_round_trip(&args, db, &npz, bytes).await?);
    }
    let text = report.join("\n") + "\n";
    print!("{text}");
    if let Some(out) = &args.out {
        std::fs::write(out, &text)?;
    }
    Ok(())
}
