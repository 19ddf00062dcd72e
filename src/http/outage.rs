//! Requests while the database is down. To its pool a PostgreSQL server that is down looks
//! busy: every request that needs a connection waits the pool's whole acquire timeout (10 s)
//! before it can be answered. Once one such wait ends in a failed fresh connection, the server
//! knows the database is down: from then on each request gets at most [`FAST_ANSWER`] to finish
//! without it (health checks, cached policies), else 503 `database_unavailable` at once, and
//! one probe a second finds out when the database is back. SQLite is never down this way.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::extract::{Request, State};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::error::ErrorCode;
use super::{ApiError, AppState};
use crate::store::Store;

/// How long a request may run while the database is known to be down.
pub const FAST_ANSWER: Duration = Duration::from_secs(1);

/// How often the database is probed while it is known to be down.
const REPROBE_EVERY: Duration = Duration::from_secs(1);

/// Whether, and since when, the database is known to be down.
#[derive(Default)]
pub struct OutageWatch {
    down: Mutex<Option<Outage>>,
    probing: AtomicBool,
}

#[derive(Clone, Copy)]
struct Outage {
    since: Instant,
    probed: Instant,
}

impl OutageWatch {
    /// Since when the database is known to be down; None while it is not.
    pub fn down_since(&self) -> Option<Instant> {
        self.down.lock().expect("outage lock").map(|o| o.since)
    }

    fn mark_down(&self) {
        let now = Instant::now();
        let mut down = self.down.lock().expect("outage lock");
        let since = down.map_or(now, |o| o.since);
        *down = Some(Outage { since, probed: now });
    }

    fn mark_up(&self) {
        if self.down.lock().expect("outage lock").take().is_some() {
            tracing::info!("the database can be reached again");
        }
    }

    /// Probes the database in the background unless a probe runs or ran within
    /// [`REPROBE_EVERY`]; a probe that connects ends the outage.
    fn reprobe(self: &Arc<Self>, store: &Store) {
        let due = self
            .down
            .lock()
            .expect("outage lock")
            .is_some_and(|o| o.probed.elapsed() >= REPROBE_EVERY);
        if !due || self.probing.swap(true, Ordering::AcqRel) {
            return;
        }
        let (watch, store) = (self.clone(), store.clone());
        tokio::spawn(async move {
            match store.database_reachable().await {
                true => watch.mark_up(),
                false => watch.mark_down(),
            }
            watch.probing.store(false, Ordering::Release);
        });
    }
}

/// Names database outages (see the module): a `database_busy` answer after which a fresh
/// connection fails is `database_unavailable`, and starts the outage; during one, requests get
/// [`FAST_ANSWER`].
pub async fn name_database_outages(
    State(state): State<AppState>,
    request: Request,
    next: Next,
) -> Response {
    let watch = &state.outage;
    if let Some(since) = watch.down_since() {
        watch.reprobe(&state.store);
        return match tokio::time::timeout(FAST_ANSWER, next.run(request)).await {
            Ok(response) if !needed_the_database(&response) => response,
            _ => known_outage(since).into_response(),
        };
    }
    let response = next.run(request).await;
    if error_code(&response) == Some("database_unavailable") {
        watch.mark_down();
    } else if error_code(&response) == Some("database_busy")
        && !state.store.database_reachable().await
    {
        tracing::warn!("the database cannot be reached; answering 503 database_unavailable");
        watch.mark_down();
        return ApiError::database_unavailable().into_response();
    }
    response
}

fn error_code(response: &Response) -> Option<&'static str> {
    response.extensions().get::<ErrorCode>().map(|c| c.0)
}

/// An answer that waited for a connection the outage will not give.
fn needed_the_database(response: &Response) -> bool {
    matches!(error_code(response), Some("database_busy" | "database_unavailable"))
}

fn known_outage(since: Instant) -> ApiError {
    ApiError::unavailable(
        "database_unavailable",
        format!(
            "the database cannot be reached: found down {} s ago and probed every second since; \
             nothing was changed, retry in a few seconds",
            since.elapsed().as_secs()
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_outage_keeps_its_start_until_the_database_is_back() {
        let watch = OutageWatch::default();
        assert!(watch.down_since().is_none());
        watch.mark_down();
        let since = watch.down_since().unwrap();
        watch.mark_down();
        assert_eq!(watch.down_since(), Some(since), "a second failure is the same outage");
        watch.mark_up();
        assert!(watch.down_since().is_none());
    }
}
