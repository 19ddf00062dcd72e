//! Notifications between the processes that share a store: PostgreSQL's NOTIFY and LISTEN. On
//! SQLite both are no-ops, and its processes poll. A notification only hastens what every
//! listener's poll does anyway, so one lost while a connection is down costs time, not data.

use std::future::Future;
use std::time::Duration;

use sqlx::postgres::PgListener;
use tokio_util::sync::CancellationToken;

use super::{Backend, Store};

impl Store {
    /// Sends `payload` to every connection listening on `channel`.
    pub async fn notify(&self, channel: &str, payload: &str) -> Result<(), sqlx::Error> {
        if self.backend == Backend::Postgres {
            sqlx::query("SELECT CAST(pg_notify($1, $2) AS TEXT)")
                .bind(channel)
                .bind(payload)
                .execute(&self.pool)
                .await?;
        }
        Ok(())
    }

    /// Hands every payload sent on `channel` to `handle`, one at a time, until `shutdown`. A
    /// connection that cannot be opened or is lost is opened again `retry` later (what was sent
    /// in between is missed: the caller's poll covers it). Returns at once on SQLite.
    pub async fn listen<F, Fut>(
        &self,
        channel: &str,
        shutdown: &CancellationToken,
        retry: Duration,
        mut handle: F,
    ) where
        F: FnMut(String) -> Fut,
        Fut: Future<Output = ()>,
    {
        let Some(url) = self.database_url() else { return };
        while !shutdown.is_cancelled() {
            if let Err(e) = listen_until_lost(url, channel, shutdown, &mut handle).await {
                tracing::warn!(channel, error = %e, "lost the notification connection; reconnecting");
            }
            tokio::select! {
                () = shutdown.cancelled() => return,
                () = tokio::time::sleep(retry) => {}
            }
        }
    }
}

/// One connection's listening: Ok at shutdown, the error once the connection fails.
async fn listen_until_lost<F, Fut>(
    url: &str,
    channel: &str,
    shutdown: &CancellationToken,
    handle: &mut F,
) -> Result<(), sqlx::Error>
where
    F: FnMut(String) -> Fut,
    Fut: Future<Output = ()>,
{
    let mut listener = PgListener::connect(url).await?;
    listener.listen(channel).await?;
    loop {
        tokio::select! {
            () = shutdown.cancelled() => return Ok(()),
            received = listener.recv() => handle(received?.payload().to_owned()).await,
        }
    }
}
