//! What stays open for long (exempt from the request timeout): a job's Server-Sent Events and
//! its log, JSON lines or followed as an event stream.

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::IntoResponse;
use futures::{Stream, StreamExt};
use serde::{Deserialize, Serialize};
use tokio::sync::broadcast;
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::Job;
use crate::domain::{rfc3339, JobId, JobProgress, LogRecord};
use crate::http::error::ErrorBody;
use crate::http::extract::{Json, Path, Query};
use crate::http::{ApiError, AppState};
use crate::jobs::JobEvent;
use crate::store::{Store, StoreError};

/// The events of `GET /v1/jobs/{id}/events` and the component schema of each one's JSON data,
/// as the OpenAPI document declares them (`itemSchema` on the stream's media type).
pub const JOB_EVENTS: [(&str, &str); 3] =
    [("status", "Job"), ("progress", "JobProgress"), ("deleted", "DeletedJob")];

/// The events of `GET /v1/jobs/{id}/logs?follow=true`, as [`JOB_EVENTS`].
pub const LOG_EVENTS: [(&str, &str); 1] = [("log", "LogLine")];

/// The data of the `deleted` event: the job's id.
#[derive(Debug, Serialize, ToSchema)]
pub struct DeletedJob {
    pub id: String,
}

pub(super) fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(job_events)).routes(routes!(job_log))
}

/// `?after=&limit=&follow=`
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct LogParams {
    /// Only lines after this line number (default 0: from the first line).
    #[param(minimum = 0)]
    pub after: Option<u64>,
    /// Most lines returned, 1 to 1000 (default 1000; without `follow`).
    #[param(minimum = 1, maximum = 1000, default = 1000)]
    pub limit: Option<u32>,
    /// Stream the lines as Server-Sent Events (`event: log`), new ones as they are written,
    /// until the job has finished and its last line was sent.
    #[serde(default)]
    pub follow: bool,
}

/// A line of a job's log.
#[derive(Debug, Serialize, ToSchema)]
pub struct LogLine {
    /// The line's number in the job's log, from 1.
    pub seq: u64,
    /// When it was written (RFC 3339).
    pub time: String,
    /// `info`, `warn` or `error`.
    pub level: String,
    /// The worker that wrote it.
    pub worker: String,
    pub message: String,
}

impl From<LogRecord> for LogLine {
    fn from(record: LogRecord) -> Self {
        LogLine {
            seq: record.seq,
            time: rfc3339(&record.time),
            level: record.level.as_str().to_owned(),
            worker: record.worker,
            message: record.message,
        }
    }
}

const LOG_LIMIT: u32 = 1000;

/// A job's log: what its workers wrote about it (claimed, resumed from a checkpoint, phases,
/// alpha-hat, evaluations, checkpoints, how it ended, why it failed). JSON lines in order, or
/// with `follow=true` an event stream that ends when the job has finished.
#[utoipa::path(get, path = "/v1/jobs/{id}/logs", tag = "jobs",
    params(("id" = String, Path), LogParams),
    responses(
        (status = 200, description = "The lines (JSON), or with `follow=true` a server-sent \
            event stream of `event: log` events whose data is a LogLine",
         content(
            (Vec<LogLine> = "application/json"),
            (String = "text/event-stream"),
         )),
        (status = 400, description = "Bad `after` or `limit`", body = ErrorBody),
        (status = 404, body = ErrorBody),
    ))]
async fn job_log(
    State(state): State<AppState>,
    Path(id): Path<JobId>,
    Query(params): Query<LogParams>,
    headers: axum::http::HeaderMap,
) -> Result<axum::response::Response, ApiError> {
    let limit = params.limit.unwrap_or(LOG_LIMIT);
    if !(1..=LOG_LIMIT).contains(&limit) {
        return Err(ApiError::bad_request(
            "invalid_limit",
            format!("limit must be between 1 and {LOG_LIMIT}, got {limit}"),
        ));
    }
    let after = i64::try_from(params.after.unwrap_or(0))
        .map_err(|_| ApiError::bad_request("invalid_after", "after must be at most 2^63 - 1"))?;
    state.store.job(&id).await?;
    if !params.follow {
        let rows = state.store.job_log(&id, after, limit).await?;
        return Ok(Json(rows.into_iter().map(LogLine::from).collect::<Vec<_>>()).into_response());
    }
    let permit = stream_permit(&state)?;
    // A client reconnecting (a stream ends after STREAM_LIFETIME) resumes after the last line
    // it saw: each line's event id is its `seq`. Subscribed before anything is read.
    let after = last_event_id(&headers).unwrap_or(after);
    let rows =
        crate::http::log_follower::follow(state.store.clone(), state.jobs.subscribe(), id, after);
    let lines = rows.map(|row| {
        let seq = row.seq.to_string();
        json_event("log", &LogLine::from(row)).id(seq)
    });
    Ok(Sse::new(bounded(lines, &state, permit)).keep_alive(KeepAlive::default()).into_response())
}

/// Server-Sent Events of a job: first a `status` event with the job resource, then `progress`
/// events (a [`JobProgress`], about twice a second while it runs) and a `status` event with the
/// job at every status change. The stream ends after a final status (`succeeded`, `failed`,
/// `cancelled`) or when the server shuts down.
#[utoipa::path(get, path = "/v1/jobs/{id}/events", tag = "jobs", params(("id" = String, Path)),
    responses(
        (status = 200, description = "`event: status` (data: Job) and `event: progress` \
            (data: JobProgress); the stream ends after a final status, or with `event: deleted` \
            (data: `{\"id\": ...}`) once the job is deleted", content_type = "text/event-stream", body = String),
        (status = 404, body = ErrorBody),
    ))]
async fn job_events(
    State(state): State<AppState>,
    Path(id): Path<JobId>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let permit = stream_permit(&state)?;
    // Subscribe before reading the job, so no change between the two is missed.
    let receiver = state.jobs.subscribe();
    let job = Job::from(state.store.job(&id).await?);
    let finished = job.status.is_final();
    let first = status_event(&job);
    let updates = futures::stream::unfold(
        (receiver, state.store.clone(), id, finished),
        |(mut receiver, store, id, finished)| async move {
            if finished {
                return None;
            }
            let event = next_event(&mut receiver, &store, &id).await?;
            let finished = match &event {
                Update::Status(job) => job.status.is_final(),
                Update::Progress(_) => false,
                Update::Deleted => true,
            };
            let event = match event {
                Update::Progress(progress) => json_event("progress", &progress),
                Update::Status(job) => status_event(&job),
                Update::Deleted => json_event("deleted", &DeletedJob { id: id.to_string() }),
            };
            Some((event, (receiver, store, id, finished)))
        },
    );
    let stream = futures::stream::once(std::future::ready(first)).chain(updates);
    Ok(Sse::new(bounded(stream, &state, permit)).keep_alive(KeepAlive::default()))
}

enum Update {
    Progress(JobProgress),
    Status(Box<Job>),
    /// The job is gone (deleted here, or on another API node).
    Deleted,
}

/// How long a stream waits for an event before it checks that its job still exists: a job
/// deleted through another API node announces nothing here.
const STREAM_CHECK: Duration = Duration::from_secs(5);

/// The next event of job `id`; None when the runner is gone or the job cannot be read.
async fn next_event(
    receiver: &mut broadcast::Receiver<JobEvent>,
    store: &Store,
    id: &JobId,
) -> Option<Update> {
    loop {
        let Ok(received) = tokio::time::timeout(STREAM_CHECK, receiver.recv()).await else {
            match store.job_status(id).await {
                Err(StoreError::NotFound { .. }) => return Some(Update::Deleted),
                _ => continue,
            }
        };
        match received {
            Ok(event) if event.job_id() != id => continue,
            Ok(JobEvent::Progress { progress, .. }) => return Some(Update::Progress(progress)),
            Ok(JobEvent::Deleted { .. }) => return Some(Update::Deleted),
            Ok(JobEvent::Status { .. }) => match store.job(id).await {
                Ok(job) => return Some(Update::Status(Box::new(job.into()))),
                Err(StoreError::NotFound { .. }) => return Some(Update::Deleted),
                Err(_) => return None,
            },
            // A slow reader skipped some progress; the next event brings it up to date.
            Err(broadcast::error::RecvError::Lagged(_)) => continue,
            Err(broadcast::error::RecvError::Closed) => return None,
        }
    }
}

/// How long one event stream stays open: clients reconnect (an EventSource does so by itself,
/// `Last-Event-ID` resumes a log), so a slot held by a forgotten tab turns over.
const STREAM_LIFETIME: Duration = Duration::from_secs(15 * 60);

/// A slot for one more event stream, or 503 `too_many_streams`.
fn stream_permit(state: &AppState) -> Result<tokio::sync::OwnedSemaphorePermit, ApiError> {
    state.streams.clone().try_acquire_owned().map_err(|_| {
        ApiError::unavailable(
            "too_many_streams",
            format!(
                "{} event streams are open already (--max-streams); retry shortly",
                state.config.max_streams
            ),
        )
    })
}

/// `events` ended by shutdown or after [`STREAM_LIFETIME`], holding `permit` while it runs.
fn bounded(
    events: impl Stream<Item = Event> + Send + 'static,
    state: &AppState,
    permit: tokio::sync::OwnedSemaphorePermit,
) -> impl Stream<Item = Result<Event, Infallible>> + Send + 'static {
    events
        .take_until(state.shutdown.clone().cancelled_owned())
        .take_until(tokio::time::sleep(STREAM_LIFETIME))
        .map(move |event| {
            let _held = &permit;
            Ok(event)
        })
}

/// The `Last-Event-ID` a reconnecting event-stream client sends.
fn last_event_id(headers: &axum::http::HeaderMap) -> Option<i64> {
    headers.get("last-event-id")?.to_str().ok()?.trim().parse().ok().filter(|id| *id >= 0)
}

fn status_event(job: &Job) -> Event {
    json_event("status", job)
}

fn json_event(name: &str, data: &impl Serialize) -> Event {
    Event::default().event(name).json_data(data).unwrap_or_else(|e| {
        tracing::error!(error = %e, "cannot serialise an event");
        Event::default().event("error").data("event serialisation failed")
    })
}
