//! Starting and stopping the service: open the store, bind the HTTP listener (and the gRPC one
//! with --grpc-bind), serve until shut down.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::config::ServeConfig;
use crate::domain::RetryBackoff;
use crate::http::connections::{self, ConnectionLimits, ConnectionSlots};
use crate::http::{self, AppState, Serving};
use crate::jobs::{JobRunner, WorkerOptions};
use crate::serving::registry::ModelRegistry;
use crate::serving::shadow::Shadows;
use crate::serving::PolicyCache;
use crate::store::Store;

/// How long a graceful shutdown waits for in-flight requests before dropping them.
pub const SHUTDOWN_GRACE: Duration = Duration::from_secs(30);

/// A running server.
pub struct Server {
    local_addr: SocketAddr,
    grpc_addr: Option<SocketAddr>,
    shutdown: CancellationToken,
    task: JoinHandle<std::io::Result<()>>,
    grpc_task: Option<JoinHandle<std::io::Result<()>>>,
    store: Store,
    jobs: JobRunner,
}

impl Server {
    /// Validates the configuration, opens (or creates) the data directory, runs migrations,
    /// binds the listener and starts serving in the background.
    pub async fn start(config: ServeConfig) -> anyhow::Result<Server> {
        config.validate()?;
        let store = Store::connect(&config.data_dir, config.database_url.as_deref()).await?;
        store.remove_leftovers().await?;
        let listener = tokio::net::TcpListener::bind(config.bind)
            .await
            .with_context(|| format!("cannot listen on {}", config.bind))?;
        let local_addr = listener.local_addr()?;
        let grpc_listener = match config.grpc_bind {
            Some(bind) => Some(
                tokio::net::TcpListener::bind(bind)
                    .await
                    .with_context(|| format!("cannot listen on {bind} (--grpc-bind)"))?,
            ),
            None => None,
        };
        let grpc_addr = grpc_listener.as_ref().map(|l| l.local_addr()).transpose()?;
        let shutdown = CancellationToken::new();
        let auth = if config.api_token.is_some() { "bearer token" } else { "none (loopback)" };
        tracing::info!(
            %local_addr,
            grpc = grpc_addr.map(|a| a.to_string()).unwrap_or_else(|| "off".into()),
            data_dir = %config.data_dir.display(),
            database = store.backend().as_str(),
            auth,
            "safedice listening"
        );
        let config_max_connections = config.max_connections as usize;
        let per_address = config.max_connections_per_address as usize;
        let header_timeout_secs = config.header_timeout_secs;
        let send_stall = (config.send_stall_timeout_secs > 0)
            .then(|| Duration::from_secs(config.send_stall_timeout_secs));
        let options = WorkerOptions::new(
            usize::from(config.workers),
            Duration::from_secs(config.lease_seconds),
            config.min_free_disk,
        )
        .with_retry_backoff(RetryBackoff::new(Duration::from_secs(config.retry_backoff_secs)))
        .with_job_threads(config.job_threads());
        let jobs = JobRunner::new(store.clone(), options, shutdown.clone());
        jobs.start(true).await?;
        let policies = Arc::new(PolicyCache::new(store.clone(), config.policy_cache_bytes));
        let shadows = Shadows::start(store.clone());
        shadows.clone().watch(shutdown.clone());
        let models = Arc::new(ModelRegistry::new(store.clone(), policies.clone(), shadows));
        // The named models are loaded before the server answers, as a model repository does.
        if let Err(e) = models.refresh_all().await {
            tracing::error!(error = %e, "cannot load the named models; they load on first use");
        }
        models.clone().watch(shutdown.clone());
        let services = Serving { policies, models };
        let state = AppState::new(config, store.clone(), jobs.clone(), services, shutdown.clone());
        let limits = ConnectionLimits::new(
            config_max_connections,
            per_address,
            Duration::from_secs(header_timeout_secs),
            send_stall,
        );
        tracing::info!(
            max_connections = limits.max_connections,
            per_address = limits.max_per_address,
            "connection limits"
        );
        // The gRPC service on its own listener, under the same connection limits, counted
        // together with REST's: the caps (and the open-file budget behind them) are the server's.
        let budget = ConnectionSlots::new(&limits);
        let grpc_task = grpc_listener.map(|grpc_listener| {
            let (app, budget) = (crate::grpc::app(state.clone()), budget.clone());
            tokio::spawn(connections::serve(grpc_listener, app, limits, budget, shutdown.clone()))
        });
        let app = http::app(state)?;
        let task =
            tokio::spawn(connections::serve(listener, app, limits, budget, shutdown.clone()));
        Ok(Server { local_addr, grpc_addr, shutdown, task, grpc_task, store, jobs })
    }

    /// The bound address (the actual port when the configuration asked for port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The gRPC listener's address (`--grpc-bind`; None when off).
    pub fn grpc_addr(&self) -> Option<SocketAddr> {
        self.grpc_addr
    }

    /// Cancelling this token starts a graceful shutdown.
    pub fn shutdown_token(&self) -> CancellationToken {
        self.shutdown.clone()
    }

    /// Stops accepting connections, lets in-flight requests finish (at most
    /// [`SHUTDOWN_GRACE`]), then closes the database.
    pub async fn stop(self) -> anyhow::Result<()> {
        self.shutdown.cancel();
        self.wait().await
    }

    /// Serves until the shutdown token is cancelled, then finishes like [`Server::stop`].
    pub async fn wait(mut self) -> anyhow::Result<()> {
        self.shutdown.cancelled().await;
        let deadline = tokio::time::Instant::now() + SHUTDOWN_GRACE;
        let served = finish(&mut self.task, deadline).await;
        let grpc_served = match &mut self.grpc_task {
            Some(task) => finish(task, deadline).await,
            None => Ok(()),
        };
        // Workers checkpoint their jobs and hand them back to the queue before the store closes.
        self.jobs.stopped().await;
        self.store.close().await;
        tracing::info!("safedice stopped");
        served.and(grpc_served)
    }
}

/// Waits for a listener's task to finish its connections until `deadline`, then drops them.
async fn finish(
    task: &mut JoinHandle<std::io::Result<()>>,
    deadline: tokio::time::Instant,
) -> anyhow::Result<()> {
    match tokio::time::timeout_at(deadline, &mut *task).await {
        Ok(joined) => joined.context("the server task failed")?.context("serving failed"),
        Err(_) => {
            tracing::warn!(
                "in-flight requests still running after the grace period; dropping them"
            );
            task.abort();
            Ok(())
        }
    }
}

/// Resolves on SIGINT (Ctrl-C) or SIGTERM with the signal's name. Callers start the shutdown
/// before they log it, so that stopping never depends on a log line.
/// Like [`shutdown_signal`], but listening from the moment it is called rather than from the
/// returned future's first poll: a signal sent right after a "ready" line printed after this
/// call is not lost (the process would otherwise die of its default action).
pub fn shutdown_listener() -> impl std::future::Future<Output = &'static str> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let listeners = (signal(SignalKind::interrupt()), signal(SignalKind::terminate()));
        async move {
            match listeners {
                (Ok(mut interrupt), Ok(mut terminate)) => tokio::select! {
                    _ = interrupt.recv() => "SIGINT",
                    _ = terminate.recv() => "SIGTERM",
                },
                _ => shutdown_signal().await,
            }
        }
    }
    #[cfg(not(unix))]
    shutdown_signal()
}

pub async fn shutdown_signal() -> &'static str {
    let interrupt = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!(error = %e, "cannot listen for SIGINT");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = interrupt => "SIGINT",
        () = terminate => "SIGTERM",
    }
}
