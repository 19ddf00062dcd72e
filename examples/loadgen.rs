//! Inference load generator: single-observation `POST /v1/policies/{id}/act` (and KServe v2
//! `infer`) requests at a fixed concurrency against a real server on loopback; prints
//! requests/s and p50/p99 latency.
//!
//! ```text
//! cargo run --release --example loadgen -- [--concurrency 8] [--seconds 10] [--url URL --policy ID]
//! ```
//! Without `--url` it starts the server in-process on a free loopback port with a fresh data
//! directory, uploads a synthetic continuous-control dataset (obs_dim 17, 6 action dims, like
//! the MuJoCo tasks), trains a BC policy of the paper's size ([256, 256]) for 200 iterations and
//! benchmarks that. The client shares the machine's cores with the server.

use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safedice::config::ServeConfig;
use safedice::data::{ActionSpace, Actions, Dataset, DatasetParts};
use safedice::server::Server;
use serde_json::{json, Value};

const OBS_DIM: usize = 17;
const ACTION_DIM: usize = 6;

struct Args {
    concurrency: usize,
    seconds: u64,
    url: Option<String>,
    policy: Option<String>,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = Args { concurrency: 8, seconds: 10, url: None, policy: None };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--concurrency" => args.concurrency = value()?.parse()?,
            "--seconds" => args.seconds = value()?.parse()?,
            "--url" => args.url = Some(value()?),
            "--policy" => args.policy = Some(value()?),
            other => bail!("unknown argument {other}"),
        }
    }
    if args.url.is_some() != args.policy.is_some() {
        bail!("--url and --policy go together");
    }
    Ok(args)
}

/// A synthetic continuous dataset: 50 episodes of 100 steps, actions a smooth function of the
/// observation plus noise, inside [-1, 1]^6.
fn synthetic_dataset() -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let (episodes, length) = (50, 100);
    let n = episodes * length;
    let observations: Vec<f32> = (0..n * OBS_DIM).map(|_| rng.random_range(-1.0..1.0)).collect();
    let mut next_observations = observations[OBS_DIM..].to_vec();
    next_observations.extend_from_slice(&observations[..OBS_DIM]);
    let actions = (0..n * ACTION_DIM)
        .map(|k| {
            let (row, j) = (k / ACTION_DIM, k % ACTION_DIM);
            let x = observations[row * OBS_DIM + j] + observations[row * OBS_DIM + j + 6];
            (x * 0.5 + rng.random_range(-0.1..0.1)).tanh()
        })
        .collect();
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
    .unwrap()
}

/// An in-process server on its own temporary data directory (removed when dropped).
struct LocalServer {
    _server: Server,
    _data_dir: tempfile::TempDir,
}

/// Starts a server in-process, trains a policy on it; returns the server, its URL and the policy.
async fn prepare_server(client: &reqwest::Client) -> anyhow::Result<(LocalServer, String, String)> {
    let data_dir = tempfile::tempdir()?;
    let dir = data_dir.path().to_path_buf();
    let mut config = ServeConfig::new(&dir);
    config.bind = "127.0.0.1:0".parse()?;
    let server = Server::start(config).await?;
    let url = format!("http://{}", server.local_addr());
    let file = dir.join("synthetic.npz");
    safedice::data::write_npz(&synthetic_dataset(), &file)?;
    let form = reqwest::multipart::Form::new().part(
        "file",
        reqwest::multipart::Part::bytes(std::fs::read(&file)?).file_name("synthetic.npz"),
    );
    let dataset: Value =
        client.post(format!("{url}/v1/datasets")).multipart(form).send().await?.json().await?;
    let job: Value = client
        .post(format!("{url}/v1/jobs"))
        .json(&json!({"algorithm": "bc", "unlabeled_dataset": dataset["id"],
                      "config": {"iterations": 200, "seed": 0}}))
        .send()
        .await?
        .json()
        .await?;
    let job_url = format!("{url}/v1/jobs/{}", job["id"].as_str().context("job id")?);
    loop {
        let job: Value = client.get(&job_url).send().await?.json().await?;
        match job["status"].as_str() {
            Some("succeeded") => {
                let policy = job["policy_id"].as_str().context("policy id")?.to_owned();
                let local = LocalServer { _server: server, _data_dir: data_dir };
                return Ok((local, url, policy));
            }
            Some("failed" | "cancelled") => bail!("training failed: {job}"),
            _ => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}

/// Runs `concurrency` clients sending one request after another for `seconds`; returns the
/// sorted latencies.
async fn hammer(
    client: &reqwest::Client,
    url: String,
    body: Value,
    concurrency: usize,
    seconds: u64,
) -> anyhow::Result<(Vec<Duration>, Duration)> {
    let started = Instant::now();
    let deadline = started + Duration::from_secs(seconds);
    let body = bytes::Bytes::from(serde_json::to_vec(&body)?);
    let clients = (0..concurrency).map(|_| {
        let (client, url, body) = (client.clone(), url.clone(), body.clone());
        tokio::spawn(async move {
            let mut latencies = Vec::new();
            while Instant::now() < deadline {
                let sent = Instant::now();
                let response = client
                    .post(&url)
                    .header("content-type", "application/json")
                    .body(body.clone())
                    .send()
                    .await?;
                if !response.status().is_success() {
                    bail!("{} answered {}", url, response.status());
                }
                response.bytes().await?;
                latencies.push(sent.elapsed());
            }
            anyhow::Ok(latencies)
        })
    });
    let mut all = Vec::new();
    for task in futures::future::join_all(clients).await {
        all.extend(task??);
    }
    all.sort_unstable();
    Ok((all, started.elapsed()))
}

fn report(name: &str, latencies: &[Duration], elapsed: Duration, concurrency: usize) {
    let quantile = |q: f64| latencies[((latencies.len() - 1) as f64 * q).round() as usize];
    println!(
        "{name:<28} concurrency {concurrency:>3}  {:>9.0} req/s  p50 {:>7.3} ms  p99 {:>7.3} ms  ({} requests)",
        latencies.len() as f64 / elapsed.as_secs_f64(),
        quantile(0.5).as_secs_f64() * 1e3,
        quantile(0.99).as_secs_f64() * 1e3,
        latencies.len(),
    );
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = parse_args()?;
    let client = reqwest::Client::builder().pool_max_idle_per_host(args.concurrency).build()?;
    let (_server, url, policy) = match (args.url.clone(), args.policy.clone()) {
        (Some(url), Some(policy)) => (None, url, policy),
        _ => {
            let (server, url, policy) = prepare_server(&client).await?;
            (Some(server), url, policy)
        }
    };
    let meta: Value = client.get(format!("{url}/v2/models/{policy}")).send().await?.json().await?;
    let obs_dim = meta["inputs"][0]["shape"][1].as_u64().context("model metadata")? as usize;
    let observation: Vec<f32> = (0..obs_dim).map(|i| (i as f32 * 0.37).sin()).collect();
    let act = json!({"observations": [observation]});
    let infer = json!({"inputs": [{"name": "observations", "datatype": "FP32",
                                   "shape": [1, obs_dim], "data": observation}]});
    println!("policy {policy} at {url}, obs_dim {obs_dim}, {} s per run", args.seconds);
    // Warm-up: loads the policy into the cache and opens the connections.
    hammer(&client, format!("{url}/v1/policies/{policy}/act"), act.clone(), args.concurrency, 1)
        .await?;
    let (latencies, elapsed) = hammer(
        &client,
        format!("{url}/v1/policies/{policy}/act"),
        act,
        args.concurrency,
        args.seconds,
    )
    .await?;
    report("POST /v1/policies/{id}/act", &latencies, elapsed, args.concurrency);
    let (latencies, elapsed) = hammer(
        &client,
        format!("{url}/v2/models/{policy}/infer"),
        infer,
        args.concurrency,
        args.seconds,
    )
    .await?;
    report("POST /v2/models/{id}/infer", &latencies, elapsed, args.concurrency);
    Ok(())
}
