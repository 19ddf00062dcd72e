//! Alias moves under load: agents hammer `POST /v1/models/pilot@production/act` while the alias
//! is moved between versions 1 and 2; version 3 exists and is never aliased. Reports, for a
//! phase without moves and one with them: requests/s, p50/p99, non-2xx answers, answers from a
//! version other than 1 or 2, and answers whose actions are not the answering version's (a
//! half-loaded model would show there); with `--nodes 2`, how long the node that did not take
//! the move kept answering from the old version. Then the open-loop latency at 25%, 50% and 75%
//! of the measured saturating throughput (requests sent on a fixed schedule, each timed from
//! when it was due, so a stalled server is charged for the requests it delayed: the
//! coordinated-omission correction).
//!
//! ```text
//! cargo build --release && cargo run --release --example alias_swap -- \
//!     [--store sqlite|postgres] [--nodes 1|2] [--connections 32] [--seconds 10] [--moves 20] \
//!     [--bin target/release/safedice]
//! ```
//! The servers are child processes of `--bin` on one store (SQLite: one data directory;
//! PostgreSQL: a throwaway cluster, Debian's `postgresql` needed); the load generator shares
//! the machine's cores with them. Exits non-zero on any non-2xx, any answer from version 3 or
//! any answer whose actions are not its version's.

#[path = "../tests/support/postgres.rs"]
#[allow(dead_code)]
mod postgres;

use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safedice::data::{ActionSpace, Actions, Dataset, DatasetParts};
use serde_json::{json, Value};

const OBS_DIM: usize = 17;
const ACTION_DIM: usize = 6;
const ACT_PATH: &str = "/v1/models/pilot@production/act";

struct Args {
    store: String,
    nodes: usize,
    connections: usize,
    seconds: u64,
    moves: usize,
    bin: String,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = Args {
        store: "sqlite".into(),
        nodes: 1,
        connections: 32,
        seconds: 10,
        moves: 20,
        bin: "target/release/safedice".into(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--store" => args.store = value()?,
            "--nodes" => args.nodes = value()?.parse()?,
            "--connections" => args.connections = value()?.parse()?,
            "--seconds" => args.seconds = value()?.parse()?,
            "--moves" => args.moves = value()?.parse()?,
            "--bin" => args.bin = value()?,
            other => bail!("unknown argument {other}"),
        }
    }
    if !["sqlite", "postgres"].contains(&args.store.as_str()) || args.nodes == 0 {
        bail!("--store is sqlite or postgres, --nodes at least 1");
    }
    Ok(args)
}

/// A `safedice serve` child process, killed when dropped.
struct Node {
    child: Child,
    url: String,
}

impl Drop for Node {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn start_node(
    args: &Args,
    data_dir: &std::path::Path,
    database: Option<&str>,
    workers: u16,
) -> anyhow::Result<Node> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
    let mut command = Command::new(&args.bin);
    command
        .args(["serve", "--bind", &format!("127.0.0.1:{port}"), "--workers"])
        .arg(workers.to_string())
        .arg("--data-dir")
        .arg(data_dir)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null());
    if let Some(url) = database {
        command.args(["--database-url", url]);
    }
    let child = command.spawn().with_context(|| format!("cannot start {}", args.bin))?;
    let node = Node { child, url: format!("http://127.0.0.1:{port}") };
    let client = reqwest::Client::new();
    for _ in 0..600 {
        if client
            .get(format!("{}/readyz", node.url))
            .send()
            .await
            .is_ok_and(|r| r.status().is_success())
        {
            return Ok(node);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    bail!("node {} did not become ready", node.url)
}

/// A continuous-control dataset of the MuJoCo tasks' widths (17 → 6).
fn synthetic_dataset() -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let (episodes, length) = (40, 100);
    let n = episodes * length;
    let observations: Vec<f32> = (0..n * OBS_DIM).map(|_| rng.random_range(-1.0..1.0)).collect();
    let actions: Vec<f32> = (0..n * ACTION_DIM)
        .map(|k| (observations[(k / ACTION_DIM) * OBS_DIM + k % ACTION_DIM]).tanh())
        .collect();
    let mut next_observations = observations[OBS_DIM..].to_vec();
    next_observations.extend_from_slice(&observations[..OBS_DIM]);
    Dataset::new(DatasetParts {
        obs_dim: OBS_DIM,
        action_space: ActionSpace::Continuous {
            dim: ACTION_DIM,
            low: vec![-1.0; ACTION_DIM],
            high: vec![1.0; ACTION_DIM],
        },
        observations,
        actions: Actions::Continuous(actions),
        next_observations,
        terminals: vec![false; n],
        episode_ids: (0..n).map(|i| (i / length) as u32).collect(),
        rewards: None,
        costs: None,
    })
    .expect("a valid dataset")
}

async fn post(client: &reqwest::Client, url: String, body: Value) -> anyhow::Result<Value> {
    let response = client.post(&url).json(&body).send().await?;
    let status = response.status();
    let body: Value = response.json().await?;
    if !status.is_success() {
        bail!("POST {url}: {status} {body}");
    }
    Ok(body)
}

/// Trains three BC policies on node 0 and registers them as versions 1-3 of `pilot`, with
/// `production` at version 1. Returns the policies' actions for the load's observation.
async fn prepare(
    client: &reqwest::Client,
    url: &str,
    body: &Value,
) -> anyhow::Result<(Vec<Value>, Vec<String>)> {
    let dir = tempfile::tempdir()?;
    let file = dir.path().join("synthetic.npz");
    safedice::data::write_npz(&synthetic_dataset(), &file)?;
    let form = reqwest::multipart::Form::new().part(
        "file",
        reqwest::multipart::Part::bytes(std::fs::read(&file)?).file_name("synthetic.npz"),
    );
    let dataset: Value =
        client.post(format!("{url}/v1/datasets")).multipart(form).send().await?.json().await?;
    post(client, format!("{url}/v1/models"), json!({"name": "pilot"})).await?;
    let (mut actions, mut policies) = (Vec::new(), Vec::new());
    for seed in 1..=3 {
        let job = post(
            client,
            format!("{url}/v1/jobs"),
            json!({"algorithm": "bc", "unlabeled_dataset": dataset["id"],
                   "config": {"iterations": 200, "seed": seed}, "register": {"model": "pilot"}}),
        )
        .await?;
        let job_url = format!("{url}/v1/jobs/{}", job["id"].as_str().context("job id")?);
        let policy = loop {
            let job: Value = client.get(&job_url).send().await?.json().await?;
            match job["status"].as_str() {
                Some("succeeded") => break job["policy_id"].as_str().context("policy")?.to_owned(),
                Some("failed" | "cancelled") => bail!("training failed: {job}"),
                _ => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        };
        let answer = post(client, format!("{url}/v1/policies/{policy}/act"), body.clone()).await?;
        actions.push(answer["actions"].clone());
        policies.push(policy);
    }
    let alias = client
        .put(format!("{url}/v1/models/pilot/aliases/production"))
        .json(&json!({"version": 1, "actor": "alias_swap"}))
        .send()
        .await?;
    if !alias.status().is_success() {
        bail!("cannot set production: {}", alias.status());
    }
    Ok((actions, policies))
}

/// What the load saw.
#[derive(Default)]
struct Tally {
    latencies: Vec<Duration>,
    failures: u64,
    third_version: u64,
    wrong_actions: u64,
}

/// `connections` clients, each on its own node (round robin), one request after another until
/// `deadline`.
async fn hammer(
    nodes: &[String],
    connections: usize,
    body: &Value,
    expected: &Arc<Vec<Value>>,
    deadline: Instant,
) -> anyhow::Result<Tally> {
    let body = bytes::Bytes::from(serde_json::to_vec(body)?);
    let tasks = (0..connections).map(|i| {
        let url = format!("{}{ACT_PATH}", nodes[i % nodes.len()]);
        let (body, expected) = (body.clone(), expected.clone());
        tokio::spawn(async move {
            let client = reqwest::Client::builder().pool_max_idle_per_host(1).build()?;
            let mut tally = Tally::default();
            while Instant::now() < deadline {
                let sent = Instant::now();
                let response = client
                    .post(&url)
                    .header("content-type", "application/json")
                    .body(body.clone())
                    .send()
                    .await?;
                check(response, &expected, &mut tally).await?;
                tally.latencies.push(sent.elapsed());
            }
            anyhow::Ok(tally)
        })
    });
    let mut all = Tally::default();
    for task in futures::future::join_all(tasks).await {
        let tally = task??;
        all.latencies.extend(tally.latencies);
        all.failures += tally.failures;
        all.third_version += tally.third_version;
        all.wrong_actions += tally.wrong_actions;
    }
    all.latencies.sort_unstable();
    Ok(all)
}

async fn check(
    response: reqwest::Response,
    expected: &[Value],
    tally: &mut Tally,
) -> anyhow::Result<()> {
    if !response.status().is_success() {
        tally.failures += 1;
        return Ok(());
    }
    let version: usize = response
        .headers()
        .get("x-safedice-model-version")
        .context("no version header")?
        .to_str()?
        .parse()?;
    let body: Value = response.json().await?;
    if version != 1 && version != 2 {
        tally.third_version += 1;
    } else if body["actions"] != expected[version - 1] {
        tally.wrong_actions += 1;
    }
    Ok(())
}

/// Moves `production` `moves` times between 1 and 2 on node 0, spread over `seconds`; after
/// each, waits until every other node answers from the new version. Returns the longest wait.
async fn mover(
    nodes: &[String],
    moves: usize,
    seconds: u64,
    body: &Value,
) -> anyhow::Result<Duration> {
    let client = reqwest::Client::new();
    let gap = Duration::from_secs(seconds) / (moves as u32 + 1);
    let mut slowest = Duration::ZERO;
    for k in 0..moves {
        tokio::time::sleep(gap).await;
        let version = if k % 2 == 0 { 2 } else { 1 };
        let moved = client
            .put(format!("{}/v1/models/pilot/aliases/production", nodes[0]))
            .json(
                &json!({"version": version, "actor": "alias_swap", "reason": format!("move {k}")}),
            )
            .send()
            .await?;
        if !moved.status().is_success() {
            bail!("move {k} answered {}", moved.status());
        }
        let committed = Instant::now();
        await_version(&client, &nodes[1..], version, body).await?;
        slowest = slowest.max(committed.elapsed());
    }
    Ok(slowest)
}

/// Waits until every node answers `production` from `version`.
async fn await_version(
    client: &reqwest::Client,
    nodes: &[String],
    version: u32,
    body: &Value,
) -> anyhow::Result<()> {
    let started = Instant::now();
    for node in nodes {
        loop {
            let answer = client.post(format!("{node}{ACT_PATH}")).json(body).send().await?;
            let header = answer.headers().get("x-safedice-model-version");
            let seen = header.and_then(|v| v.to_str().ok()?.parse::<u32>().ok());
            if seen == Some(version) {
                break;
            }
            if started.elapsed() > Duration::from_secs(10) {
                bail!("{node} answers from version {seen:?}, not {version}, after 10 s");
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
    Ok(())
}

fn quantile(latencies: &[Duration], q: f64) -> f64 {
    latencies[((latencies.len() - 1) as f64 * q).round() as usize].as_secs_f64() * 1e3
}

fn report(name: &str, tally: &Tally, seconds: u64) -> f64 {
    let rate = tally.latencies.len() as f64 / seconds as f64;
    println!(
        "| {name} | {rate:.0} | {:.2} | {:.2} | {} | {} | {} |",
        quantile(&tally.latencies, 0.5),
        quantile(&tally.latencies, 0.99),
        tally.failures,
        tally.third_version,
        tally.wrong_actions
    );
    rate
}

/// Requests due at `rate` per second for `seconds`, sent over `connections` keep-alive
/// connections (each takes the oldest due request when it is free, as wrk2 does), each timed
/// from when it was due: a request that waited for a free connection because the server was
/// slow is charged that wait.
async fn open_loop(
    url: String,
    rate: f64,
    seconds: u64,
    connections: usize,
    body: &Value,
) -> anyhow::Result<(Vec<Duration>, u64)> {
    let body = bytes::Bytes::from(serde_json::to_vec(body)?);
    let total = (rate * seconds as f64) as u64;
    // The schedule is kept by an OS thread (its sleeps wake within tens of microseconds; the
    // runtime's timer rounds to milliseconds, which would be charged to the server).
    let (due_tx, due_rx) = tokio::sync::mpsc::unbounded_channel::<Instant>();
    let due_rx = Arc::new(tokio::sync::Mutex::new(due_rx));
    let start = Instant::now();
    std::thread::spawn(move || {
        for k in 0..total {
            let due = start + Duration::from_secs_f64(k as f64 / rate);
            std::thread::sleep(due.saturating_duration_since(Instant::now()));
            if due_tx.send(due).is_err() {
                return;
            }
        }
    });
    let tasks = (0..connections).map(|_| {
        let (url, body, due_rx) = (url.clone(), body.clone(), due_rx.clone());
        tokio::spawn(async move {
            let client = reqwest::Client::builder().pool_max_idle_per_host(1).build()?;
            let (mut latencies, mut failed) = (Vec::new(), 0u64);
            loop {
                let Some(due) = due_rx.lock().await.recv().await else { break };
                let sent = client.post(&url).header("content-type", "application/json");
                let ok = match sent.body(body.clone()).send().await {
                    Ok(response) => {
                        response.status().is_success() && response.bytes().await.is_ok()
                    }
                    Err(_) => false,
                };
                failed += u64::from(!ok);
                latencies.push(due.elapsed());
            }
            anyhow::Ok((latencies, failed))
        })
    });
    let (mut latencies, mut failed) = (Vec::new(), 0);
    for task in futures::future::join_all(tasks).await {
        let (some, f) = task??;
        latencies.extend(some);
        failed += f;
    }
    latencies.sort_unstable();
    Ok((latencies, failed))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = parse_args()?;
    let data_dir = tempfile::tempdir()?;
    let database = match args.store.as_str() {
        "postgres" => {
            Some(postgres::cluster().context("PostgreSQL is not installed")?.new_database().await)
        }
        _ => None,
    };
    let mut nodes = vec![start_node(&args, data_dir.path(), database.as_deref(), 1).await?];
    for _ in 1..args.nodes {
        nodes.push(start_node(&args, data_dir.path(), database.as_deref(), 0).await?);
    }
    let urls: Vec<String> = nodes.iter().map(|n| n.url.clone()).collect();
    let observation: Vec<f32> = (0..OBS_DIM).map(|i| (i as f32 * 0.37).sin()).collect();
    let body = json!({"observations": [observation]});
    let client = reqwest::Client::new();
    let (expected, policies) = prepare(&client, &urls[0], &body).await?;
    let expected = Arc::new(expected);
    if expected[0] == expected[1] {
        bail!("versions 1 and 2 act alike: the check could not tell them apart");
    }
    // Every node answers from version 1 before the load starts.
    await_version(&client, &urls, 1, &body).await?;
    println!(
        "{} node(s) on {}, {} connections, {} s per phase, {} moves; CPU: see /proc/cpuinfo\n",
        args.nodes, args.store, args.connections, args.seconds, args.moves
    );
    println!("| phase | req/s | p50 ms | p99 ms | non-2xx | from version 3 | wrong actions |");
    println!("|---|---|---|---|---|---|---|");
    let deadline = Instant::now() + Duration::from_secs(args.seconds);
    let steady = hammer(&urls, args.connections, &body, &expected, deadline).await?;
    let saturating = report("no moves", &steady, args.seconds);
    let deadline = Instant::now() + Duration::from_secs(args.seconds);
    let (swapping, slowest) = tokio::join!(
        hammer(&urls, args.connections, &body, &expected, deadline),
        mover(&urls, args.moves, args.seconds, &body)
    );
    let swapping = swapping?;
    report(&format!("{} moves", args.moves), &swapping, args.seconds);
    if args.nodes > 1 {
        println!(
            "\nslowest propagation of a move to the other node(s): {:.0} ms",
            slowest?.as_secs_f64() * 1e3
        );
    } else {
        slowest?;
    }
    println!("\nopen loop on node 0 (latency from each request's due time):\n");
    println!("| rate | req/s | p50 ms | p99 ms | failed |");
    println!("|---|---|---|---|---|");
    let by_name = format!("{}{ACT_PATH}", urls[0]);
    let by_id = format!("{}/v1/policies/{}/act", urls[0], policies[0]);
    for (share, url, route) in [
        (0.25, &by_name, "by name"),
        (0.5, &by_name, "by name"),
        (0.75, &by_name, "by name"),
        (0.5, &by_id, "by policy id"),
    ] {
        let rate = saturating * share / args.nodes as f64;
        let (latencies, failed) =
            open_loop(url.clone(), rate, args.seconds, args.connections, &body).await?;
        println!(
            "| {:.0}% {route} | {rate:.0} | {:.2} | {:.2} | {failed} |",
            share * 100.0,
            quantile(&latencies, 0.5),
            quantile(&latencies, 0.99)
        );
    }
    let bad = steady.failures + swapping.failures + swapping.third_version + swapping.wrong_actions;
    if bad > 0 {
        bail!("{bad} bad answers");
    }
    Ok(())
}
