//! Latency of one action per request over each transport: REST `POST /v1/policies/{id}/act`,
//! REST `POST /v2/models/{id}/infer` (JSON), gRPC `ModelInfer` (raw tensors, as
//! tritonclient.grpc sends them) and gRPC `ModelStreamInfer` (one stream per agent).
//!
//! - **Closed loop**: one agent on one connection sends each request when the previous answer
//!   came back: the round trip.
//! - **Open loop** (`--rates`): requests fall due at a fixed rate, whatever the answers do, and
//!   `--agents` agents (each with its own connection, or its own stream) take the oldest due
//!   one when they are free, as wrk2 does; each is timed from when it was due, so a request
//!   that waited behind a slow server is charged the wait. The load generator shares the
//!   machine's cores with the server.
//!
//! - **A shadow's cost** (`--shadow SAMPLE` with `--rates`): REST `/act` by alias in the open
//!   loop, without a shadow and then with a shadow version on SAMPLE of the requests
//!   (docs/shadow.md), each rate both ways; and what the shadow's series counted (compared,
//!   skipped, its time per request).
//!
//! ```text
//! cargo build --release && cargo run --release --example grpc_latency -- \
//!     [--requests 5000] [--rates 2000,5000] [--seconds 5] [--agents 16] [--shadow 1.0] \
//!     [--bin target/release/safedice]
//! ```
//! The server is a child process of `--bin` (`serve --grpc-bind`), with a BC policy of the
//! default 256-256 network on a 17 → 6 synthetic dataset (MuJoCo widths).

use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use safedice::data::{ActionSpace, Actions, Dataset, DatasetParts};
use safedice::grpc::proto::grpc_inference_service_client::GrpcInferenceServiceClient;
use safedice::grpc::proto::model_infer_request::InferInputTensor;
use safedice::grpc::proto::ModelInferRequest;
use serde_json::{json, Value};

const OBS_DIM: usize = 17;
const ACTION_DIM: usize = 6;

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

fn dataset() -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let n = 4000;
    let observations: Vec<f32> = (0..n * OBS_DIM).map(|_| rng.random_range(-1.0..1.0)).collect();
    let actions: Vec<f32> = (0..n * ACTION_DIM)
        .map(|k| observations[(k / ACTION_DIM) * OBS_DIM + k % ACTION_DIM])
        .collect();
    let mut next_observations = observations[OBS_DIM..].to_vec();
    next_observations.extend_from_slice(&observations[..OBS_DIM]);
    let bounds = vec![1.0; ACTION_DIM];
    Dataset::new(DatasetParts {
        obs_dim: OBS_DIM,
        action_space: ActionSpace::Continuous {
            dim: ACTION_DIM,
            low: bounds.iter().map(|b| -b).collect(),
            high: bounds,
        },
        observations,
        actions: Actions::Continuous(actions),
        next_observations,
        terminals: vec![false; n],
        episode_ids: (0..n).map(|i| (i / 100) as u32).collect(),
        rewards: None,
        costs: None,
    })
    .expect("a valid dataset")
}

/// Uploads the dataset, trains a BC policy; its id.
async fn policy(client: &reqwest::Client, url: &str, seed: u64) -> anyhow::Result<String> {
    let dir = tempfile::tempdir()?;
    let file = dir.path().join("synthetic.npz");
    safedice::data::write_npz(&dataset(), &file)?;
    let part = reqwest::multipart::Part::bytes(std::fs::read(&file)?).file_name("synthetic.npz");
    let form = reqwest::multipart::Form::new().part("file", part);
    let dataset: Value =
        client.post(format!("{url}/v1/datasets")).multipart(form).send().await?.json().await?;
    let body = json!({"algorithm": "bc", "unlabeled_dataset": dataset["id"],
                      "config": {"iterations": 200, "seed": seed}});
    let job: Value = client.post(format!("{url}/v1/jobs")).json(&body).send().await?.json().await?;
    let job_url = format!("{url}/v1/jobs/{}", job["id"].as_str().context("job id")?);
    loop {
        let job: Value = client.get(&job_url).send().await?.json().await?;
        match job["status"].as_str() {
            Some("succeeded") => return Ok(job["policy_id"].as_str().context("policy")?.into()),
            Some("failed" | "cancelled") => bail!("training failed: {job}"),
            _ => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}

fn report(name: &str, mut latencies: Vec<Duration>) {
    latencies.sort_unstable();
    let at = |q: f64| latencies[((latencies.len() - 1) as f64 * q) as usize].as_secs_f64() * 1e6;
    let total: Duration = latencies.iter().sum();
    println!(
        "{name:<34} p50 {:>7.1} µs   p99 {:>7.1} µs   {:>7.0} requests/s",
        at(0.5),
        at(0.99),
        latencies.len() as f64 / total.as_secs_f64()
    );
}

/// Times `requests` calls of `call`, after a tenth as many unmeasured.
async fn timed<F: std::future::Future<Output = anyhow::Result<()>>>(
    requests: usize,
    mut call: impl FnMut() -> F,
) -> anyhow::Result<Vec<Duration>> {
    for _ in 0..requests / 10 {
        call().await?;
    }
    let mut latencies = Vec::with_capacity(requests);
    for _ in 0..requests {
        let sent = Instant::now();
        call().await?;
        latencies.push(sent.elapsed());
    }
    Ok(latencies)
}

/// Times `requests` JSON posts of `body` to `url`.
async fn rest(
    client: &reqwest::Client,
    requests: usize,
    url: String,
    body: &Value,
) -> anyhow::Result<Vec<Duration>> {
    let body = serde_json::to_vec(body)?;
    timed(requests, || {
        let request = client.post(&url).header("content-type", "application/json");
        let sent = request.body(body.clone()).send();
        async move { sent.await?.error_for_status()?.bytes().await.map(drop).map_err(Into::into) }
    })
    .await
}

/// The due times of requests at `rate` per second for `seconds`, kept by an OS thread (its
/// sleeps wake within tens of microseconds; the runtime's timer rounds to milliseconds, which
/// would be charged to the server).
fn schedule(
    rate: f64,
    seconds: u64,
) -> Arc<tokio::sync::Mutex<tokio::sync::mpsc::UnboundedReceiver<Instant>>> {
    let (due_tx, due_rx) = tokio::sync::mpsc::unbounded_channel::<Instant>();
    let total = (rate * seconds as f64) as u64;
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
    Arc::new(tokio::sync::Mutex::new(due_rx))
}

/// An agent of the open loop: answers one request per call.
trait Agent: Send + 'static {
    fn call(&mut self) -> impl std::future::Future<Output = anyhow::Result<()>> + Send;
}

struct RestAgent {
    client: reqwest::Client,
    url: String,
    body: bytes::Bytes,
}

impl Agent for RestAgent {
    async fn call(&mut self) -> anyhow::Result<()> {
        let request = self.client.post(&self.url).header("content-type", "application/json");
        let response = request.body(self.body.clone()).send().await?.error_for_status()?;
        response.bytes().await.map(drop).map_err(Into::into)
    }
}

struct UnaryAgent {
    client: GrpcInferenceServiceClient<tonic::transport::Channel>,
    message: ModelInferRequest,
}

impl Agent for UnaryAgent {
    async fn call(&mut self) -> anyhow::Result<()> {
        self.client.model_infer(self.message.clone()).await.map(drop).map_err(Into::into)
    }
}

struct StreamAgent {
    sender: tokio::sync::mpsc::Sender<ModelInferRequest>,
    answers: tonic::Streaming<safedice::grpc::proto::ModelStreamInferResponse>,
    message: ModelInferRequest,
}

impl StreamAgent {
    async fn open(
        client: &GrpcInferenceServiceClient<tonic::transport::Channel>,
        message: &ModelInferRequest,
    ) -> anyhow::Result<StreamAgent> {
        let (sender, receiver) = tokio::sync::mpsc::channel::<ModelInferRequest>(1);
        let outgoing =
            futures::stream::unfold(receiver, |mut r| async { r.recv().await.map(|m| (m, r)) });
        let answers = client.clone().model_stream_infer(outgoing).await?.into_inner();
        Ok(StreamAgent { sender, answers, message: message.clone() })
    }
}

impl Agent for StreamAgent {
    async fn call(&mut self) -> anyhow::Result<()> {
        self.sender.send(self.message.clone()).await?;
        let answer = self.answers.message().await?.context("the stream ended")?;
        if !answer.error_message.is_empty() {
            bail!("stream error: {}", answer.error_message);
        }
        Ok(())
    }
}

/// The open loop at `rate` for `seconds` with these agents: every latency (from the due time)
/// and the number of failed requests.
async fn open_loop(
    agents: Vec<impl Agent>,
    rate: f64,
    seconds: u64,
) -> anyhow::Result<(Vec<Duration>, u64)> {
    let due = schedule(rate, seconds);
    let tasks = agents.into_iter().map(|mut agent| {
        let due = due.clone();
        tokio::spawn(async move {
            let (mut latencies, mut failed) = (Vec::new(), 0u64);
            loop {
                let Some(at) = due.lock().await.recv().await else { break };
                failed += u64::from(agent.call().await.is_err());
                latencies.push(at.elapsed());
            }
            (latencies, failed)
        })
    });
    let (mut latencies, mut failed) = (Vec::new(), 0);
    for task in futures::future::join_all(tasks).await {
        let (some, f) = task?;
        latencies.extend(some);
        failed += f;
    }
    Ok((latencies, failed))
}

fn report_open(name: &str, rate: f64, seconds: u64, (mut latencies, failed): (Vec<Duration>, u64)) {
    latencies.sort_unstable();
    let at = |q: f64| latencies[((latencies.len() - 1) as f64 * q) as usize].as_secs_f64() * 1e6;
    println!(
        "| {name} | {rate:.0} | {:.0} | {:.1} | {:.1} | {failed} |",
        latencies.len() as f64 / seconds as f64,
        at(0.5),
        at(0.99)
    );
}

struct Args {
    requests: usize,
    rates: Vec<f64>,
    seconds: u64,
    agents: usize,
    shadow: Option<f64>,
    bin: String,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut args = std::env::args().skip(1);
    let mut parsed = Args {
        requests: 5000,
        rates: Vec::new(),
        seconds: 5,
        agents: 16,
        shadow: None,
        bin: "target/release/safedice".to_owned(),
    };
    while let Some(flag) = args.next() {
        let value = args.next().context("a flag needs a value")?;
        match flag.as_str() {
            "--requests" => parsed.requests = value.parse()?,
            "--rates" => {
                parsed.rates = value.split(',').map(str::parse).collect::<Result<_, _>>()?
            }
            "--seconds" => parsed.seconds = value.parse()?,
            "--agents" => parsed.agents = value.parse()?,
            "--shadow" => parsed.shadow = Some(value.parse()?),
            "--bin" => parsed.bin = value,
            other => bail!("unknown flag {other}"),
        }
    }
    Ok(parsed)
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let Args { requests, rates, seconds, agents, shadow, bin } = parse_args()?;
    let (port, grpc_port) = (free_port()?, free_port()?);
    let data = tempfile::tempdir()?;
    let _server = Server(
        Command::new(&bin)
            .args(["serve", "--bind", &format!("127.0.0.1:{port}")])
            .args(["--grpc-bind", &format!("127.0.0.1:{grpc_port}"), "--data-dir"])
            .arg(data.path())
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .with_context(|| format!("cannot start {bin}"))?,
    );
    let url = format!("http://127.0.0.1:{port}");
    let client = reqwest::Client::builder().pool_max_idle_per_host(1).build()?;
    for _ in 0..600 {
        if client.get(format!("{url}/readyz")).send().await.is_ok_and(|r| r.status().is_success()) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let policy = policy(&client, &url, 0).await?;
    let observation: Vec<f32> = (0..OBS_DIM).map(|i| i as f32 / OBS_DIM as f32).collect();
    if let Some(sample) = shadow {
        let act = json!({"observations": [observation]});
        return shadow_cost(&client, &url, &policy, sample, &act, (&rates, seconds, agents)).await;
    }
    println!("one observation per request, {requests} requests, one connection each");

    let act = json!({"observations": [observation]});
    let latencies =
        rest(&client, requests, format!("{url}/v1/policies/{policy}/act"), &act).await?;
    report("REST /v1/policies/{id}/act", latencies);
    let infer = json!({"inputs": [{"name": "observations", "shape": [1, OBS_DIM],
                                   "datatype": "FP32", "data": observation}]});
    let latencies =
        rest(&client, requests, format!("{url}/v2/models/{policy}/infer"), &infer).await?;
    report("REST /v2/models/{id}/infer (JSON)", latencies);

    let channel = tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{grpc_port}"))?
        .connect()
        .await?;
    let grpc = GrpcInferenceServiceClient::new(channel);
    let raw: Vec<u8> = observation.iter().flat_map(|v| v.to_le_bytes()).collect();
    let message = ModelInferRequest {
        model_name: policy.clone(),
        inputs: vec![InferInputTensor {
            name: "observations".into(),
            datatype: "FP32".into(),
            shape: vec![1, OBS_DIM as i64],
            ..Default::default()
        }],
        raw_input_contents: vec![raw.into()],
        ..Default::default()
    };
    let latencies = timed(requests, || {
        let (mut grpc, message) = (grpc.clone(), message.clone());
        async move { grpc.model_infer(message).await.map(drop).map_err(Into::into) }
    })
    .await?;
    report("gRPC ModelInfer (raw)", latencies);

    let (sender, receiver) = tokio::sync::mpsc::channel::<ModelInferRequest>(1);
    let outgoing =
        futures::stream::unfold(receiver, |mut r| async { r.recv().await.map(|m| (m, r)) });
    let mut answers = grpc.clone().model_stream_infer(outgoing).await?.into_inner();
    let answers = tokio::sync::Mutex::new(&mut answers);
    let latencies = timed(requests, || {
        let (sender, message, answers) = (sender.clone(), message.clone(), &answers);
        async move {
            sender.send(message).await?;
            let answer = answers.lock().await.message().await?.context("the stream ended")?;
            if !answer.error_message.is_empty() {
                bail!("stream error: {}", answer.error_message);
            }
            Ok(())
        }
    })
    .await?;
    report("gRPC ModelStreamInfer (raw)", latencies);
    if rates.is_empty() {
        return Ok(());
    }

    let endpoint =
        tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{grpc_port}"))?;
    println!("\nopen loop, {agents} agents, {seconds} s per rate (latency from the due time):\n");
    println!("| route | rate | answered/s | p50 µs | p99 µs | failed |");
    println!("|---|---|---|---|---|---|");
    for &rate in &rates {
        let act_url = format!("{url}/v1/policies/{policy}/act");
        let body = bytes::Bytes::from(serde_json::to_vec(&act)?);
        let rest_agents = (0..agents)
            .map(|_| {
                let client = reqwest::Client::builder().pool_max_idle_per_host(1).build()?;
                anyhow::Ok(RestAgent { client, url: act_url.clone(), body: body.clone() })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let tally = open_loop(rest_agents, rate, seconds).await?;
        report_open("REST /act", rate, seconds, tally);
        let mut unary = Vec::with_capacity(agents);
        for _ in 0..agents {
            let client = GrpcInferenceServiceClient::new(endpoint.connect().await?);
            unary.push(UnaryAgent { client, message: message.clone() });
        }
        let tally = open_loop(unary, rate, seconds).await?;
        report_open("gRPC ModelInfer", rate, seconds, tally);
        let channel = endpoint.connect().await?;
        let client = GrpcInferenceServiceClient::new(channel);
        let mut streams = Vec::with_capacity(agents);
        for _ in 0..agents {
            streams.push(StreamAgent::open(&client, &message).await?);
        }
        let tally = open_loop(streams, rate, seconds).await?;
        report_open("gRPC ModelStreamInfer", rate, seconds, tally);
    }
    Ok(())
}

/// REST `/act` by alias in the open loop at each rate, without and with a shadow on `sample` of
/// the requests; then what the shadow's series counted.
async fn shadow_cost(
    client: &reqwest::Client,
    url: &str,
    production: &str,
    sample: f64,
    act: &Value,
    (rates, seconds, agents): (&[f64], u64, usize),
) -> anyhow::Result<()> {
    let candidate = policy(client, url, 1).await?;
    client.post(format!("{url}/v1/models")).json(&json!({"name": "bench"})).send().await?;
    for id in [production, candidate.as_str()] {
        let registered = json!({"policy_id": id});
        client.post(format!("{url}/v1/models/bench/versions")).json(&registered).send().await?;
    }
    let alias = format!("{url}/v1/models/bench/aliases/production");
    let move_to = |body: Value| {
        let request = client.put(&alias).json(&body).send();
        async move { anyhow::Ok(request.await?.error_for_status().map(drop)?) }
    };
    let act_url = format!("{url}/v1/models/bench@production/act");
    let body = bytes::Bytes::from(serde_json::to_vec(act)?);
    println!("\nopen loop, {agents} agents, {seconds} s per rate, REST /act by alias:\n");
    println!("| route | rate | answered/s | p50 µs | p99 µs | failed |");
    println!("|---|---|---|---|---|---|");
    for &rate in rates {
        for with_shadow in [false, true] {
            let target = match with_shadow {
                true => json!({"version": 1, "shadow": {"version": 2, "sample": sample}}),
                false => json!({"version": 1}),
            };
            move_to(target).await?;
            let rest_agents = (0..agents)
                .map(|_| {
                    let client = reqwest::Client::builder().pool_max_idle_per_host(1).build()?;
                    anyhow::Ok(RestAgent { client, url: act_url.clone(), body: body.clone() })
                })
                .collect::<anyhow::Result<Vec<_>>>()?;
            let tally = open_loop(rest_agents, rate, seconds).await?;
            let name = match with_shadow {
                true => format!("REST /act, shadow on {}%", sample * 100.0),
                false => "REST /act, no shadow".to_owned(),
            };
            report_open(&name, rate, seconds, tally);
        }
    }
    let report: Value =
        client.get(format!("{url}/v1/models/bench/shadow")).send().await?.json().await?;
    for series in report["series"].as_array().context("series")? {
        let total = &series["total"];
        println!(
            "\nshadow v{} beside v{}: {} requests drawn, {} skipped, {} failed; {:.4} ms per \
             request on the shadow thread; mean L2 {:.4}",
            series["shadow_version"],
            series["production_version"],
            total["requests"],
            total["skipped"],
            total["failed"],
            total["mean_shadow_ms"].as_f64().unwrap_or(f64::NAN),
            total["mean_l2"].as_f64().unwrap_or(f64::NAN),
        );
    }
    Ok(())
}
