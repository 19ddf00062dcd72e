//! Closed-loop latency of one agent asking for one action at a time, over each transport, on
//! one connection: REST `POST /v1/policies/{id}/act`, REST `POST /v2/models/{id}/infer` (JSON),
//! gRPC `ModelInfer` (raw tensors, as tritonclient.grpc sends them) and gRPC `ModelStreamInfer`
//! (one request, its answer, the next, on one stream). Each request is sent when the previous
//! answer came back, so this measures the round trip, not the throughput under load (the
//! open-loop comparison at fixed rates is issue 38's benchmark, not this).
//!
//! ```text
//! cargo build --release && cargo run --release --example grpc_latency -- \
//!     [--requests 5000] [--bin target/release/safedice]
//! ```
//! The server is a child process of `--bin` (`serve --grpc-bind`), with a BC policy of the
//! default 256-256 network on a 17 → 6 synthetic dataset (MuJoCo widths).

use std::process::{Child, Command, Stdio};
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
async fn policy(client: &reqwest::Client, url: &str) -> anyhow::Result<String> {
    let dir = tempfile::tempdir()?;
    let file = dir.path().join("synthetic.npz");
    safedice::data::write_npz(&dataset(), &file)?;
    let part = reqwest::multipart::Part::bytes(std::fs::read(&file)?).file_name("synthetic.npz");
    let form = reqwest::multipart::Form::new().part("file", part);
    let dataset: Value =
        client.post(format!("{url}/v1/datasets")).multipart(form).send().await?.json().await?;
    let body = json!({"algorithm": "bc", "unlabeled_dataset": dataset["id"],
                      "config": {"iterations": 200, "seed": 0}});
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

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let (mut requests, mut bin) = (5000, "target/release/safedice".to_owned());
    while let Some(flag) = args.next() {
        let value = args.next().context("a flag needs a value")?;
        match flag.as_str() {
            "--requests" => requests = value.parse()?,
            "--bin" => bin = value,
            other => bail!("unknown flag {other}"),
        }
    }
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
    let policy = policy(&client, &url).await?;
    let observation: Vec<f32> = (0..OBS_DIM).map(|i| i as f32 / OBS_DIM as f32).collect();
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
    Ok(())
}
