//! `safedice demo`: the whole service in one command for a newcomer. Starts the server
//! in-process on a temporary directory, generates a small dataset from a built-in environment,
//! uploads it, trains SafeDICE and BC through the real HTTP API, evaluates both policies with the
//! paper's metrics through `POST /v1/policies/{id}/evaluate`, and prints the metrics side by
//! side together with the curl commands that do the same against a running `safedice serve`.
//! With `--serve` the service stays up afterwards, with its data, for the dashboard.

use std::io::Write;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context};
use serde_json::{json, Value};

use crate::algo::Algorithm;
use crate::config::ServeConfig;
use crate::domain::{EvaluationStatus, JobStatus};
use crate::envs::{self, DatagenSpec, Metrics};
use crate::server::Server;

/// `safedice demo` arguments.
#[derive(Clone, Debug, clap::Args)]
pub struct DemoArgs {
    /// Built-in environment to generate data from.
    #[arg(long, default_value = "six-rooms")]
    pub env: String,
    /// Policy-learning iterations of each job (SafeDICE first trains its discriminator for as
    /// many steps). At 1500 iterations with a discriminator phase of 150 steps SafeDICE did not
    /// beat BC on six-rooms.
    #[arg(long, default_value_t = 10_000)]
    pub iterations: u64,
    /// Evaluation episodes per policy.
    #[arg(long, default_value_t = 200)]
    pub episodes: usize,
    /// Seed of the data, the training runs and the evaluations.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Keep the service running after the demo, until Ctrl-C, to look at the jobs, policies and
    /// evaluations in the dashboard; the data stays in --data-dir.
    #[arg(long)]
    pub serve: bool,
    /// Where the service keeps its data. Default: a temporary directory deleted when the demo
    /// ends; with --serve, ./safedice-demo (kept, and reused by the next `demo --serve`).
    #[arg(long, value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
    /// Address to serve on. Default: a free port on 127.0.0.1; with --serve, 127.0.0.1:8080.
    #[arg(long, value_name = "ADDR")]
    pub bind: Option<SocketAddr>,
}

impl DemoArgs {
    /// The demo's defaults (what `safedice demo` runs), for tests and callers.
    pub fn new(env: &str, iterations: u64, episodes: usize) -> Self {
        DemoArgs {
            env: env.into(),
            iterations,
            episodes,
            seed: 0,
            serve: false,
            data_dir: None,
            bind: None,
        }
    }
}

/// Default data directory of `demo --serve`.
const SERVE_DATA_DIR: &str = "safedice-demo";
/// Default address of `demo --serve`.
const SERVE_BIND: &str = "127.0.0.1:8080";

/// The curl commands the demo's requests correspond to, printed at the end.
struct Transcript {
    base: String,
    lines: Vec<String>,
}

impl Transcript {
    fn record(&mut self, line: String) {
        println!("  $ {line}");
        self.lines.push(line);
    }
}

/// Runs the demo on a fresh Tokio runtime.
pub fn run_cli(args: &DemoArgs) -> anyhow::Result<()> {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(run(args)).map(|_| ())
}

/// One trained policy's evaluation, as the demo prints it.
#[derive(Clone, Debug)]
pub struct DemoRow {
    pub algorithm: Algorithm,
    /// The job's alpha-hat (SafeDICE only).
    pub alpha_hat: Option<f64>,
    /// Episodes the evaluation ran.
    pub episodes: usize,
    /// The paper's metrics, as `GET /v1/evaluations/{id}` returned them.
    pub metrics: Metrics,
}

/// The demo on the current Tokio runtime: serve, upload, train over HTTP, evaluate, print.
pub async fn run(args: &DemoArgs) -> anyhow::Result<Vec<DemoRow>> {
    let temporary = tempfile::tempdir()?;
    let dir = match (&args.data_dir, args.serve) {
        (Some(dir), _) => dir.clone(),
        (None, true) => PathBuf::from(SERVE_DATA_DIR),
        (None, false) => temporary.path().to_owned(),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut config = ServeConfig::new(dir.join("data"));
    config.bind = match args.bind {
        Some(bind) => bind,
        None if args.serve => SERVE_BIND.parse()?,
        None => "127.0.0.1:0".parse()?,
    };
    config.workers = 2;
    let bind = config.bind;
    let server = Server::start(config)
        .await
        .with_context(|| format!("cannot serve on {bind} (choose another with --bind)"))?;
    let base = format!("http://{}", server.local_addr());
    let kept = if args.data_dir.is_some() || args.serve {
        format!("data in {}", dir.display())
    } else {
        "data in a temporary directory, deleted at the end; --serve keeps it".to_owned()
    };
    println!("safedice service running at {base} ({kept})\n");
    let result = drive(args, &base, &dir).await;
    if args.serve && result.is_ok() {
        // Listen before saying so: a SIGTERM right after the line must stop us cleanly.
        let stop = crate::server::shutdown_listener();
        // From here on stdout may be a pipe its reader has closed (`| head`, a supervisor that
        // stopped reading): println! would panic and take the service down, so errors are
        // ignored and the message goes out in one write.
        let _ = write!(
            std::io::stdout(),
            "\nThe service keeps running: open {base}/ in a browser for the dashboard (jobs,\n\
             metrics, policies, evaluations). Ctrl-C stops it; the data stays in {}.\n",
            dir.display()
        );
        let _ = std::io::stdout().flush();
        let signal = stop.await;
        let _ = writeln!(std::io::stdout(), "{signal}: stopping");
    }
    server.stop().await?;
    result
}

async fn drive(args: &DemoArgs, base: &str, dir: &Path) -> anyhow::Result<Vec<DemoRow>> {
    let client = reqwest::Client::new();
    let mut transcript = Transcript { base: base.to_string(), lines: Vec::new() };

    println!("1. Generating demonstrations from `{}`", args.env);
    let spec = DatagenSpec {
        env: args.env.clone(),
        preferred: 80,
        non_preferred: 120,
        labeled: 20,
        seed: args.seed,
    };
    let generated = envs::generate(&spec)?;
    let files = dir.join("demo-data");
    let manifest = envs::write_generated(&generated, &files, crate::data::Format::Npz)?;
    println!(
        "   unlabeled: {} preferred (mean cost {:.2}) + {} non-preferred (mean cost {:.2}) \
         episodes, shuffled; labeled non-preferred: {} episodes",
        manifest.unlabeled_preferred.episodes,
        manifest.unlabeled_preferred.mean_cost,
        manifest.unlabeled_non_preferred.episodes,
        manifest.unlabeled_non_preferred.mean_cost,
        manifest.labeled_non_preferred.episodes
    );
    transcript.record(format!(
        "safedice datagen --env {} --preferred 80 --non-preferred 120 --labeled 20 --seed {} --out demo-data",
        args.env, args.seed
    ));

    println!("\n2. Uploading both sets");
    let unlabeled = upload(&client, &mut transcript, &files, "unlabeled").await?;
    let non_preferred = upload(&client, &mut transcript, &files, "non_preferred").await?;

    println!("\n3. Training SafeDICE and BC (both jobs run side by side)");
    let config = json!({"iterations": args.iterations, "seed": args.seed,
                        "hidden_sizes": [64, 64], "batch_size": 256});
    let mut jobs = Vec::new();
    for algorithm in [Algorithm::Safedice, Algorithm::Bc] {
        let mut body = json!({"algorithm": algorithm, "unlabeled_dataset": unlabeled,
                              "config": config,
                              "name": format!("demo {} on {}", algorithm.display_name(), args.env),
                              "tags": ["demo", format!("env={}", args.env)]});
        if algorithm.needs_non_preferred() {
            body["non_preferred_dataset"] = json!(non_preferred);
        }
        let job = post_json(&client, &mut transcript, "/v1/jobs", &body).await?;
        let id = job["id"].as_str().context("job without id")?.to_string();
        jobs.push((algorithm, id));
    }
    let mut finished = Vec::new();
    for (algorithm, id) in &jobs {
        transcript.record(format!("curl -s {base}/v1/jobs/{id}"));
        let job = wait_for_job(&client, base, id).await?;
        finished.push((*algorithm, job));
    }

    println!(
        "\n4. Evaluating both policies on `{}` ({} episodes, in the background)",
        args.env, args.episodes
    );
    let mut rows = Vec::new();
    for (algorithm, job) in &finished {
        let policy_id = job["policy_id"].as_str().context("succeeded job without a policy")?;
        let body = json!({"env": args.env, "episodes": args.episodes, "seed": args.seed});
        let path = format!("/v1/policies/{policy_id}/evaluate");
        let queued = post_json(&client, &mut transcript, &path, &body).await?;
        let id = queued["id"].as_str().context("evaluation without id")?;
        transcript.record(format!("curl -s {base}/v1/evaluations/{id}"));
        let evaluation = wait_for_evaluation(&client, base, id).await?;
        let metrics = serde_json::from_value(evaluation["metrics"].clone())
            .context("a succeeded evaluation without metrics")?;
        rows.push(DemoRow {
            algorithm: *algorithm,
            alpha_hat: job["alpha_hat"].as_f64(),
            episodes: evaluation["episodes"].as_u64().context("evaluation without episodes")?
                as usize,
            metrics,
        });
    }
    let (_, first) = &finished[0];
    let first_policy = first["policy_id"].as_str().unwrap_or_default();
    let obs_dim = generated.unlabeled.obs_dim();
    let observation: Vec<f32> = generated.unlabeled.obs(0).to_vec();
    let act = post_json(
        &client,
        &mut transcript,
        &format!("/v1/policies/{first_policy}/act"),
        &json!({"observations": [observation]}),
    )
    .await?;
    println!("   /act on the first observation ({obs_dim} values) answered {}", act["actions"]);

    print_table(&rows);
    if args.serve {
        println!("\nThe same with curl, against this service:");
    } else {
        println!(
            "\nThe same with curl against your own `safedice serve` (this demo's service stops \
             now; `safedice demo --serve` keeps it), with its address in place of {}:",
            transcript.base
        );
    }
    for line in &transcript.lines {
        println!("  {line}");
    }
    Ok(rows)
}

async fn upload(
    client: &reqwest::Client,
    transcript: &mut Transcript,
    dir: &Path,
    stem: &str,
) -> anyhow::Result<String> {
    let file = format!("{stem}.npz");
    let bytes = std::fs::read(dir.join(&file))?;
    let form = reqwest::multipart::Form::new()
        .part("file", reqwest::multipart::Part::bytes(bytes).file_name(file.clone()))
        .text("name", stem.to_string())
        .text("role", stem.to_string());
    let url = format!("{}/v1/datasets", transcript.base);
    transcript
        .record(format!("curl -s -F file=@demo-data/{file} -F name={stem} -F role={stem} {url}"));
    let response = client.post(&url).multipart(form).send().await?;
    let body = checked_json(response).await?;
    let id = body["id"].as_str().context("dataset without id")?.to_string();
    println!("   -> dataset {id}");
    Ok(id)
}

async fn post_json(
    client: &reqwest::Client,
    transcript: &mut Transcript,
    path: &str,
    body: &Value,
) -> anyhow::Result<Value> {
    let url = format!("{}{path}", transcript.base);
    transcript.record(format!("curl -s -H 'content-type: application/json' -d '{body}' {url}"));
    checked_json(client.post(&url).json(body).send().await?).await
}

async fn checked_json(response: reqwest::Response) -> anyhow::Result<Value> {
    let status = response.status();
    let body: Value = response.json().await.context("response is not JSON")?;
    if !status.is_success() {
        bail!("HTTP {status}: {body}");
    }
    Ok(body)
}

/// Polls `GET /v1/jobs/{id}` until the job succeeds, printing its progress.
async fn wait_for_job(client: &reqwest::Client, base: &str, id: &str) -> anyhow::Result<Value> {
    let mut last_print = std::time::Instant::now();
    loop {
        let job = checked_json(client.get(format!("{base}/v1/jobs/{id}")).send().await?).await?;
        match job["status"].as_str().and_then(|s| s.parse::<JobStatus>().ok()) {
            Some(JobStatus::Succeeded) => {
                println!("   job {id} ({}) succeeded", job["algorithm"]);
                return Ok(job);
            }
            Some(JobStatus::Failed | JobStatus::Cancelled | JobStatus::Discarded) => {
                bail!("job {id} ended: {job}")
            }
            _ => {}
        }
        if last_print.elapsed() > Duration::from_secs(5) {
            println!(
                "   job {id} ({}): step {} of {}",
                job["algorithm"], job["progress"]["step"], job["progress"]["total"]
            );
            last_print = std::time::Instant::now();
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// Polls `GET /v1/evaluations/{id}` until the evaluation succeeds.
async fn wait_for_evaluation(
    client: &reqwest::Client,
    base: &str,
    id: &str,
) -> anyhow::Result<Value> {
    loop {
        let url = format!("{base}/v1/evaluations/{id}");
        let evaluation = checked_json(client.get(url).send().await?).await?;
        match evaluation["status"].as_str().and_then(|s| s.parse::<EvaluationStatus>().ok()) {
            Some(EvaluationStatus::Succeeded) => return Ok(evaluation),
            Some(EvaluationStatus::Failed) => {
                bail!("evaluation {id} failed: {}", evaluation["error"])
            }
            _ => tokio::time::sleep(Duration::from_millis(100)).await,
        }
    }
}

fn print_table(rows: &[DemoRow]) {
    print!("\n{}", table(rows));
}

/// The demo's results as it prints them (and as README's "Benchmark and demo" quotes them).
pub fn table(rows: &[DemoRow]) -> String {
    let mut text = format!(
        "{:<10} {:>14} {:>13} {:>15} {:>13} {:>10}\n",
        "algorithm", "norm. return", "avg cost", "violation ratio", "CVaR 10%", "alpha-hat"
    );
    for DemoRow { algorithm, alpha_hat: alpha, metrics: m, .. } in rows {
        text.push_str(&format!(
            "{:<10} {:>14.1} {:>13.2} {:>15.3} {:>13.2} {:>10}\n",
            algorithm.display_name(),
            m.normalized_return,
            m.average_cost,
            m.cost_violation_ratio,
            m.cvar_cost.k10,
            alpha.map_or("-".to_string(), |a| format!("{a:.4}"))
        ));
    }
    text
}
