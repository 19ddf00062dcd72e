//! Soak benchmark: concurrent clients mixing every kind of request against a real
//! `safedice serve` child process for minutes; reports the request count, every answer that is
//! neither 2xx nor 4xx, the server's resident memory over time (it must plateau), and whether
//! every upload and job the server accepted is still listed at the end (minus the ones the
//! clients deleted).
//!
//! ```text
//! cargo build --release && cargo run --release --example soak -- \
//!     [--clients 8] [--seconds 300] [--workers 2] [--nodes 1] [--bin target/release/safedice]
//! ```
//! `--nodes 2` starts two `safedice serve` processes on one SQLite data directory (the
//! one-machine fleet the docs allow) and spreads the clients over them: no "database is locked"
//! may surface as a 5xx, and nothing accepted by either node may go missing.
//!
//! A fleet on PostgreSQL: `--database-url postgres://… --nodes 2 --workers 0
//! --worker-processes 2 --kill-every 120` starts two API nodes (`serve --workers 0`) and two
//! `safedice worker` processes, each with a data directory of its own, and SIGKILLs one worker
//! every 120 s (a new one takes its place). At the end every job still queued or running is
//! cancelled, and each job must have ended exactly once: a final status, and for a succeeded
//! job exactly one succeeded attempt and a policy. Every process's RSS and open descriptors are
//! sampled every 10 s.
//! The mix per client step: upload a small dataset (one in five invalid), submit a short job
//! (BC or SafeDICE), cancel a job, delete a dataset (refused while a job uses it), read a job's
//! metrics, list jobs, follow a job's events for a moment, `/act` on a trained policy, and churn
//! a model of its own: create it with a version of one of two trained policies and point
//! `prod` at it, act on `name@prod` through another API node, or delete the alias and the model
//! and create them again on the other policy. An answer from the other node must come from the
//! policy the model has now once [`ROUTE_GRACE`] has passed since the change (the nodes follow
//! within about a second: notification, or the 1 s poll).
//! Exits non-zero on any 5xx, any transport error, anything accepted and then missing, a job
//! that did not end exactly once, or a stale route.

use std::collections::{BTreeMap, BTreeSet};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{json, Value};

const OBS_DIM: usize = 4;

/// How long after a model changed an API node may still answer from what it had before: the
/// 1 s poll, and slack for a machine whose cores the soak keeps busy.
const ROUTE_GRACE: Duration = Duration::from_secs(3);

struct Args {
    clients: usize,
    seconds: u64,
    workers: u16,
    nodes: usize,
    bin: String,
    /// PostgreSQL: every process on this database, each with a data directory of its own.
    database_url: Option<String>,
    worker_processes: usize,
    /// Seconds between two SIGKILLs of a worker process (0: never).
    kill_every: u64,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = Args {
        clients: 8,
        seconds: 300,
        workers: 2,
        nodes: 1,
        bin: "target/release/safedice".into(),
        database_url: None,
        worker_processes: 0,
        kill_every: 0,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--clients" => args.clients = value()?.parse()?,
            "--seconds" => args.seconds = value()?.parse()?,
            "--workers" => args.workers = value()?.parse()?,
            "--nodes" => args.nodes = value()?.parse()?,
            "--bin" => args.bin = value()?,
            "--database-url" => args.database_url = Some(value()?),
            "--worker-processes" => args.worker_processes = value()?.parse()?,
            "--kill-every" => args.kill_every = value()?.parse()?,
            other => bail!("unknown argument {other}"),
        }
    }
    Ok(args)
}

/// A process under test (an API node or a worker), killed when dropped.
struct ServerProcess {
    child: Child,
    url: String,
    name: String,
}

impl ServerProcess {
    /// A `safedice serve` with `--workers` from the arguments.
    async fn start(
        args: &Args,
        data_dir: &std::path::Path,
        name: String,
    ) -> anyhow::Result<ServerProcess> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let bind = format!("127.0.0.1:{port}");
        let serve = ["serve", "--bind", &bind, "--workers", &args.workers.to_string()];
        let server = ServerProcess::spawn(args, &serve, data_dir, name, format!("http://{bind}"))?;
        let started = Instant::now();
        while reqwest::get(format!("{}/healthz", server.url)).await.is_err() {
            if started.elapsed() > Duration::from_secs(60) {
                bail!("the server did not come up");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        Ok(server)
    }

    /// A `safedice worker` process.
    fn worker(
        args: &Args,
        data_dir: &std::path::Path,
        name: String,
    ) -> anyhow::Result<ServerProcess> {
        ServerProcess::spawn(args, &["worker"], data_dir, name, String::new())
    }

    fn spawn(
        args: &Args,
        command: &[&str],
        data_dir: &std::path::Path,
        name: String,
        url: String,
    ) -> anyhow::Result<ServerProcess> {
        let mut child = Command::new(&args.bin);
        child.args(command).arg("--data-dir").arg(data_dir);
        if let Some(database) = &args.database_url {
            child.args(["--database-url", database]);
        }
        let child = child
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .with_context(|| format!("cannot start {} (build it first)", args.bin))?;
        Ok(ServerProcess { child, url, name })
    }

    /// Resident memory now, in MiB.
    fn rss_mib(&self) -> f64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))
            .unwrap_or_default();
        let kib: f64 = status
            .lines()
            .find(|l| l.starts_with("VmRSS:"))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0.0);
        kib / 1024.0
    }

    /// Open file descriptors now.
    fn open_fds(&self) -> usize {
        std::fs::read_dir(format!("/proc/{}/fd", self.child.id())).map_or(0, |d| d.count())
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// What the clients saw, shared between them.
#[derive(Default)]
struct Ledger {
    requests: u64,
    by_status: BTreeMap<u16, u64>,
    by_kind: BTreeMap<&'static str, u64>,
    failures: Vec<String>,
    datasets: BTreeSet<String>,
    deleted_datasets: BTreeSet<String>,
    jobs: BTreeSet<String>,
    models_created: u64,
    model_acts: u64,
    model_acts_in_grace: u64,
}

impl Ledger {
    fn record(&mut self, kind: &'static str, status: u16) {
        self.requests += 1;
        *self.by_status.entry(status).or_default() += 1;
        *self.by_kind.entry(kind).or_default() += 1;
        if !(200..500).contains(&status) {
            self.failures.push(format!("{kind}: {status}"));
        }
    }
}

/// A small JSONL dataset of `episodes` × 20 transitions; `valid` false makes one row ragged.
fn jsonl_dataset(rng: &mut ChaCha8Rng, episodes: usize, valid: bool) -> Vec<u8> {
    let mut out = String::new();
    for episode in 0..episodes {
        for t in 0..20 {
            let obs: Vec<f32> = (0..OBS_DIM).map(|_| rng.random_range(-1.0..1.0)).collect();
            let next: Vec<f32> = (0..OBS_DIM).map(|_| rng.random_range(-1.0..1.0)).collect();
            let action = (obs[0] * 0.5).tanh();
            let obs = if !valid && episode == 1 && t == 3 { &obs[..2] } else { &obs[..] };
            let row = json!({"episode": episode, "obs": obs, "action": [action],
                "next_obs": next, "reward": 1.0, "cost": f32::from(t % 5 == 0),
                "terminal": t == 19});
            out.push_str(&row.to_string());
            out.push('\n');
        }
    }
    out.into_bytes()
}

struct Client {
    http: reqwest::Client,
    url: String,
    rng: ChaCha8Rng,
    ledger: Arc<Mutex<Ledger>>,
    policy: String,
    /// The two policies the client's model alternates between.
    policies: [String; 2],
    /// Another API node (the same one with a single node), where the model is acted on.
    other_url: String,
    model: String,
    /// The model's current policy (index into `policies`) and when it last changed.
    model_state: Option<(usize, Instant)>,
}

impl Client {
    fn pick<'a>(&mut self, set: &'a [String]) -> Option<&'a String> {
        (!set.is_empty()).then(|| &set[self.rng.random_range(0..set.len())])
    }

    fn known(&self) -> (Vec<String>, Vec<String>) {
        let ledger = self.ledger.lock().unwrap();
        let live = ledger.datasets.difference(&ledger.deleted_datasets).cloned().collect();
        (live, ledger.jobs.iter().cloned().collect())
    }

    async fn send(
        &mut self,
        kind: &'static str,
        request: reqwest::RequestBuilder,
    ) -> anyhow::Result<(u16, Value)> {
        let response = match request.send().await {
            Ok(response) => response,
            Err(e) => {
                self.ledger.lock().unwrap().failures.push(format!("{kind}: transport {e}"));
                return Ok((0, Value::Null));
            }
        };
        let status = response.status().as_u16();
        let body = response.json::<Value>().await.unwrap_or(Value::Null);
        self.ledger.lock().unwrap().record(kind, status);
        Ok((status, body))
    }

    async fn step(&mut self) -> anyhow::Result<()> {
        let (datasets, jobs) = self.known();
        let url = self.url.clone();
        match self.rng.random_range(0..100) {
            0..=14 => {
                let valid = self.rng.random_range(0..5) != 0;
                let episodes = self.rng.random_range(2..6);
                let bytes = jsonl_dataset(&mut self.rng, episodes, valid);
                let form = reqwest::multipart::Form::new()
                    .part("file", reqwest::multipart::Part::bytes(bytes).file_name("soak.jsonl"));
                let request = self.http.post(format!("{url}/v1/datasets")).multipart(form);
                let (status, body) = self.send("upload", request).await?;
                if status == 201 {
                    let id = body["id"].as_str().context("dataset id")?.to_owned();
                    self.ledger.lock().unwrap().datasets.insert(id);
                }
            }
            15..=29 => {
                let Some(dataset) = self.pick(&datasets).cloned() else { return Ok(()) };
                let algorithm = if self.rng.random_bool(0.5) { "bc" } else { "safedice" };
                let mut body = json!({"algorithm": algorithm, "unlabeled_dataset": dataset,
                    "config": {"iterations": self.rng.random_range(50..400), "seed": 0,
                               "hidden_sizes": [32, 32], "batch_size": 64}});
                if algorithm == "safedice" {
                    body["non_preferred_dataset"] = json!(dataset);
                }
                let request = self.http.post(format!("{url}/v1/jobs")).json(&body);
                let (status, body) = self.send("submit", request).await?;
                if status == 201 {
                    let id = body["id"].as_str().context("job id")?.to_owned();
                    self.ledger.lock().unwrap().jobs.insert(id);
                }
            }
            30..=39 => {
                let Some(job) = self.pick(&jobs).cloned() else { return Ok(()) };
                let request = self.http.post(format!("{url}/v1/jobs/{job}/cancel"));
                self.send("cancel", request).await?;
            }
            40..=47 => {
                let Some(dataset) = self.pick(&datasets).cloned() else { return Ok(()) };
                let request = self.http.delete(format!("{url}/v1/datasets/{dataset}"));
                let (status, _) = self.send("delete", request).await?;
                if status == 204 {
                    self.ledger.lock().unwrap().deleted_datasets.insert(dataset);
                }
            }
            48..=62 => {
                let Some(job) = self.pick(&jobs).cloned() else { return Ok(()) };
                let request = self.http.get(format!("{url}/v1/jobs/{job}/metrics?max_points=200"));
                self.send("metrics", request).await?;
            }
            63..=66 => {
                let request = self.http.get(format!("{url}/v1/jobs?limit=100"));
                self.send("list", request).await?;
            }
            70..=79 => self.churn_model().await?,
            67..=69 => {
                let Some(job) = self.pick(&jobs).cloned() else { return Ok(()) };
                self.follow_events(&format!("{url}/v1/jobs/{job}/events")).await;
            }
            _ => {
                let obs: Vec<f32> =
                    (0..OBS_DIM).map(|_| self.rng.random_range(-1.0..1.0)).collect();
                let request = self
                    .http
                    .post(format!("{url}/v1/policies/{}/act", self.policy))
                    .json(&json!({"observations": [obs], "deterministic": true}));
                self.send("act", request).await?;
            }
        }
        Ok(())
    }
}

impl Client {
    /// One step of the model churn (see the module's docs).
    async fn churn_model(&mut self) -> anyhow::Result<()> {
        match self.model_state {
            None => self.create_model(0).await,
            Some((current, _)) if self.rng.random_range(0..4) == 0 => {
                let (url, model) = (self.url.clone(), self.model.clone());
                let alias = self.http.delete(format!("{url}/v1/models/{model}/aliases/prod"));
                self.send("model delete", alias).await?;
                let (status, _) = self
                    .send("model delete", self.http.delete(format!("{url}/v1/models/{model}")))
                    .await?;
                if status != 204 {
                    self.note_failure(format!("model delete: {status}"));
                }
                self.create_model(1 - current).await
            }
            Some((current, changed)) => {
                let obs: Vec<f32> = vec![0.1; OBS_DIM];
                let url = format!("{}/v1/models/{}@prod/act", self.other_url, self.model);
                let request = self.http.post(url).json(&json!({"observations": [obs]}));
                let response = match request.send().await {
                    Ok(response) => response,
                    Err(e) => {
                        self.note_failure(format!("model act: transport {e}"));
                        return Ok(());
                    }
                };
                let status = response.status().as_u16();
                self.ledger.lock().unwrap().record("model act", status);
                let answered = response
                    .headers()
                    .get("x-safedice-policy-id")
                    .and_then(|v| v.to_str().ok())
                    .map(str::to_owned);
                let settled = changed.elapsed() > ROUTE_GRACE;
                let stale = match (status, answered) {
                    (200, Some(policy)) => policy != self.policies[current],
                    (404, _) => true,
                    _ => false,
                };
                if settled && stale {
                    let after = changed.elapsed();
                    self.note_failure(format!(
                        "model act: {} answered {status} from a stale route {after:?} after the \
                         change",
                        self.model
                    ));
                }
                let mut ledger = self.ledger.lock().unwrap();
                ledger.model_acts += 1;
                if stale && !settled {
                    ledger.model_acts_in_grace += 1;
                }
                Ok(())
            }
        }
    }

    /// Creates the client's model with one version of `policies[which]` and `prod` on it.
    async fn create_model(&mut self, which: usize) -> anyhow::Result<()> {
        let (url, model) = (self.url.clone(), self.model.clone());
        let steps = [
            (self.http.post(format!("{url}/v1/models")).json(&json!({"name": model})), 201),
            (
                self.http
                    .post(format!("{url}/v1/models/{model}/versions"))
                    .json(&json!({"policy_id": self.policies[which]})),
                201,
            ),
            (
                self.http
                    .put(format!("{url}/v1/models/{model}/aliases/prod"))
                    .json(&json!({"version": 1, "actor": "soak"})),
                200,
            ),
        ];
        for (request, expected) in steps {
            let (status, body) = self.send("model create", request).await?;
            if status != expected {
                self.note_failure(format!("model create: {status} {body}"));
                return Ok(());
            }
        }
        self.model_state = Some((which, Instant::now()));
        self.ledger.lock().unwrap().models_created += 1;
        Ok(())
    }

    fn note_failure(&self, failure: String) {
        self.ledger.lock().unwrap().failures.push(failure);
    }

    /// Opens a job's event stream and reads it for up to a second (a dashboard tab that comes
    /// and goes).
    async fn follow_events(&mut self, url: &str) {
        use futures::StreamExt;
        let response = match self.http.get(url).send().await {
            Ok(response) => response,
            Err(e) => {
                self.ledger.lock().unwrap().failures.push(format!("events: transport {e}"));
                return;
            }
        };
        self.ledger.lock().unwrap().record("events", response.status().as_u16());
        let mut body = response.bytes_stream();
        let _ = tokio::time::timeout(Duration::from_secs(1), async {
            while body.next().await.is_some() {}
        })
        .await;
    }
}

/// Trains the policy the `/act` requests use.
async fn train_policy(http: &reqwest::Client, url: &str, seed: u64) -> anyhow::Result<String> {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let form = reqwest::multipart::Form::new().part(
        "file",
        reqwest::multipart::Part::bytes(jsonl_dataset(&mut rng, 10, true)).file_name("p.jsonl"),
    );
    let dataset: Value =
        http.post(format!("{url}/v1/datasets")).multipart(form).send().await?.json().await?;
    let job: Value = http
        .post(format!("{url}/v1/jobs"))
        .json(&json!({"algorithm": "bc", "unlabeled_dataset": dataset["id"],
                      "config": {"iterations": 100, "seed": seed, "hidden_sizes": [32, 32]}}))
        .send()
        .await?
        .json()
        .await?;
    let job_url = format!("{url}/v1/jobs/{}", job["id"].as_str().context("job id")?);
    loop {
        let job: Value = http.get(&job_url).send().await?.json().await?;
        match job["status"].as_str() {
            Some("succeeded") => return Ok(job["policy_id"].as_str().context("policy")?.into()),
            Some("failed" | "cancelled" | "discarded") => bail!("training failed: {job}"),
            _ => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}

/// Every id of a list endpoint, following its pages.
async fn list_all(
    http: &reqwest::Client,
    url: &str,
    path: &str,
) -> anyhow::Result<BTreeSet<String>> {
    let mut ids = BTreeSet::new();
    let mut offset = 0u64;
    loop {
        let page: Value =
            http.get(format!("{url}{path}?limit=500&offset={offset}")).send().await?.json().await?;
        for item in page["items"].as_array().context("items")? {
            ids.insert(item["id"].as_str().context("id")?.to_owned());
        }
        match page["next_offset"].as_u64() {
            Some(next) => offset = next,
            None => return Ok(ids),
        }
    }
}

/// The processes of the run: API nodes and worker processes, with their data directories.
struct Processes {
    nodes: Vec<ServerProcess>,
    workers: Vec<ServerProcess>,
    root: tempfile::TempDir,
    started_workers: usize,
}

impl Processes {
    async fn start(args: &Args) -> anyhow::Result<Processes> {
        let root = tempfile::tempdir()?;
        // SQLite: one shared data directory; PostgreSQL: one each, as a fleet runs.
        let dir = |name: &str| match args.database_url {
            Some(_) => root.path().join(name),
            None => root.path().join("shared"),
        };
        let mut nodes = Vec::new();
        for i in 0..args.nodes.max(1) {
            let name = format!("api-{}", i + 1);
            nodes.push(ServerProcess::start(args, &dir(&name), name).await?);
        }
        let mut processes = Processes { nodes, workers: Vec::new(), root, started_workers: 0 };
        for _ in 0..args.worker_processes {
            processes.start_worker(args)?;
        }
        Ok(processes)
    }

    fn start_worker(&mut self, args: &Args) -> anyhow::Result<()> {
        self.started_workers += 1;
        let name = format!("worker-{}", self.started_workers);
        let dir = self.root.path().join(&name);
        self.workers.push(ServerProcess::worker(args, &dir, name)?);
        Ok(())
    }

    /// SIGKILLs the oldest worker process and starts a new one in its place.
    fn kill_a_worker(&mut self, args: &Args) -> anyhow::Result<String> {
        if self.workers.is_empty() {
            bail!("no worker process to kill");
        }
        let killed = self.workers.remove(0);
        let name = killed.name.clone();
        drop(killed);
        self.start_worker(args)?;
        Ok(name)
    }

    fn all(&self) -> impl Iterator<Item = &ServerProcess> {
        self.nodes.iter().chain(&self.workers)
    }
}

/// Cancels every job not yet final, waits until all are, and returns the jobs that did not end
/// exactly once (not final, or succeeded without exactly one succeeded attempt and a policy).
async fn jobs_not_ended_once(
    http: &reqwest::Client,
    url: &str,
    jobs: &BTreeSet<String>,
) -> anyhow::Result<Vec<String>> {
    const FINAL: [&str; 3] = ["succeeded", "failed", "cancelled"];
    for id in jobs {
        let _ = http.post(format!("{url}/v1/jobs/{id}/cancel")).send().await?;
    }
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut wrong = Vec::new();
    for id in jobs {
        let job = loop {
            let job: Value = http.get(format!("{url}/v1/jobs/{id}")).send().await?.json().await?;
            if FINAL.contains(&job["status"].as_str().unwrap_or("")) || Instant::now() > deadline {
                break job;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        };
        let status = job["status"].as_str().unwrap_or("?").to_owned();
        if !FINAL.contains(&status.as_str()) {
            wrong.push(format!("{id}: still {status}"));
            continue;
        }
        let attempts: Value =
            http.get(format!("{url}/v1/jobs/{id}/attempts")).send().await?.json().await?;
        let succeeded = attempts["attempts"]
            .as_array()
            .map_or(0, |a| a.iter().filter(|a| a["outcome"] == "succeeded").count());
        let expected = usize::from(status == "succeeded");
        if succeeded != expected || (status == "succeeded") != job["policy_id"].is_string() {
            wrong.push(format!("{id}: {status} with {succeeded} succeeded attempts"));
        }
    }
    Ok(wrong)
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = parse_args()?;
    let mut processes = Processes::start(&args).await?;
    let node_urls: Vec<String> = processes.nodes.iter().map(|n| n.url.clone()).collect();
    let url = node_urls[0].clone();
    let http = reqwest::Client::builder().timeout(Duration::from_secs(60)).build()?;
    let policy = train_policy(&http, &url, 0).await?;
    let other_policy = train_policy(&http, &url, 1).await?;
    let ledger = Arc::new(Mutex::new(Ledger::default()));
    let started = Instant::now();
    let deadline = started + Duration::from_secs(args.seconds);
    let clients: Vec<_> = (0..args.clients)
        .map(|i| {
            let mut client = Client {
                http: http.clone(),
                url: node_urls[i % node_urls.len()].clone(),
                rng: ChaCha8Rng::seed_from_u64(100 + i as u64),
                ledger: ledger.clone(),
                policy: policy.clone(),
                policies: [policy.clone(), other_policy.clone()],
                other_url: node_urls[(i + 1) % node_urls.len()].clone(),
                model: format!("soak-model-{i}"),
                model_state: None,
            };
            tokio::spawn(async move {
                while Instant::now() < deadline {
                    client.step().await?;
                }
                anyhow::Ok(())
            })
        })
        .collect();
    let names: Vec<String> = processes.all().map(|p| p.name.clone()).collect();
    println!(
        "every 10 s: requests so far, then RSS (MiB) / open fds of each process ({})",
        names.join(", ")
    );
    let mut samples = Vec::new();
    let mut next_kill =
        (args.kill_every > 0).then(|| started + Duration::from_secs(args.kill_every));
    while Instant::now() < deadline {
        tokio::time::sleep(Duration::from_secs(10).min(deadline - Instant::now())).await;
        if next_kill.is_some_and(|at| Instant::now() >= at) {
            let killed = processes.kill_a_worker(&args)?;
            println!("  SIGKILL {killed}; started worker-{}", processes.started_workers);
            next_kill = next_kill.map(|at| at + Duration::from_secs(args.kill_every));
        }
        let rss: Vec<f64> = processes.all().map(ServerProcess::rss_mib).collect();
        let cells: Vec<String> = processes
            .all()
            .zip(&rss)
            .map(|(p, rss)| format!("{} {rss:.0}/{}", p.name, p.open_fds()))
            .collect();
        let requests = ledger.lock().unwrap().requests;
        println!(
            "{:>5.0} s {:>8}  {}",
            started.elapsed().as_secs_f64(),
            requests,
            cells.join("  ")
        );
        // The API nodes' (workers come and go): each must plateau.
        samples.push(rss[..processes.nodes.len()].iter().cloned().fold(0.0, f64::max));
    }
    for client in clients {
        client.await??;
    }
    let elapsed = started.elapsed().as_secs_f64();
    let listed_datasets = list_all(&http, &url, "/v1/datasets").await?;
    let listed_jobs = list_all(&http, &url, "/v1/jobs").await?;
    let jobs = ledger.lock().unwrap().jobs.clone();
    let not_once = if args.database_url.is_some() {
        jobs_not_ended_once(&http, &url, &jobs).await?
    } else {
        Vec::new()
    };
    let ledger = ledger.lock().unwrap();
    let expected: BTreeSet<_> =
        ledger.datasets.difference(&ledger.deleted_datasets).cloned().collect();
    let missing_datasets: Vec<_> = expected.difference(&listed_datasets).collect();
    let missing_jobs: Vec<_> = ledger.jobs.difference(&listed_jobs).collect();
    println!(
        "\n{} requests in {elapsed:.0} s ({:.1}/s) from {} clients, {} API node(s) with \
         --workers {}, {} worker process(es) ({} started in all)",
        ledger.requests,
        ledger.requests as f64 / elapsed,
        args.clients,
        processes.nodes.len(),
        args.workers,
        processes.workers.len(),
        processes.started_workers,
    );
    println!("by kind:   {:?}", ledger.by_kind);
    println!("by status: {:?}", ledger.by_status);
    println!(
        "accepted: {} uploads ({} deleted), {} jobs; missing afterwards: {} datasets, {} jobs",
        ledger.datasets.len(),
        ledger.deleted_datasets.len(),
        ledger.jobs.len(),
        missing_datasets.len(),
        missing_jobs.len()
    );
    if args.database_url.is_some() {
        println!("jobs that did not end exactly once: {}", not_once.len());
        for job in not_once.iter().take(20) {
            println!("  {job}");
        }
    }
    let third = samples.len() / 3;
    if third > 0 {
        let mean = |s: &[f64]| s.iter().sum::<f64>() / s.len() as f64;
        println!(
            "API nodes' RSS: first third {:.1} MiB, last third {:.1} MiB, max {:.1} MiB",
            mean(&samples[..third]),
            mean(&samples[samples.len() - third..]),
            samples.iter().cloned().fold(0.0, f64::max)
        );
    }
    println!(
        "models: {} created (each delete and create again counts), {} acts through another node \
         ({} answered from the route before a change within {ROUTE_GRACE:?} of it)",
        ledger.models_created, ledger.model_acts, ledger.model_acts_in_grace
    );
    println!(
        "failures (neither 2xx nor 4xx, transport, or a stale route): {}",
        ledger.failures.len()
    );
    for failure in ledger.failures.iter().take(20) {
        println!("  {failure}");
    }
    if !ledger.failures.is_empty()
        || !missing_datasets.is_empty()
        || !missing_jobs.is_empty()
        || !not_once.is_empty()
    {
        bail!("the soak found failures");
    }
    Ok(())
}
