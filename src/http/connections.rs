//! Accepting connections, with the limits that keep slow or idle clients from exhausting the
//! process: a cap on open connections (below the file-descriptor limit, so the database and
//! uploads always find descriptors), a deadline for a request's headers (slowloris; it also
//! closes keep-alive connections left idle that long), and a deadline between two pieces of a
//! request body (a body that trickles one byte per minute). `axum::serve` has none of these
//! knobs, so this is its loop on `hyper-util` with them set.

use std::io;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;

/// Descriptors kept free for everything that is not a client connection: the database pool
/// and its WAL, upload temp files, dataset reads, the log.
const RESERVED_DESCRIPTORS: u64 = 64;

/// How long accepting pauses after the kernel refuses a descriptor (EMFILE/ENFILE).
const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);

/// errno values of "too many open files" for the process (EMFILE) and the system (ENFILE).
const EMFILE: i32 = 24;
const ENFILE: i32 = 23;

/// The limits in force for client connections.
#[derive(Clone, Copy, Debug)]
pub struct ConnectionLimits {
    /// Open client connections at most; more are answered 503 at once ([`SHED_AT_ONCE`] at a time).
    pub max_connections: usize,
    /// Open connections from one IP address at most; more from it are answered 503 at once.
    pub max_per_address: usize,
    /// A request's headers must arrive within this (also the keep-alive idle limit).
    pub header_read_timeout: Duration,
}

impl ConnectionLimits {
    /// `configured`, lowered to what the process's open-file limit leaves after
    /// [`RESERVED_DESCRIPTORS`]. Raises the soft limit to the hard one first, as servers do.
    pub fn new(configured: usize, per_address: usize, header_read_timeout: Duration) -> Self {
        let descriptors = rlimit::increase_nofile_limit(u64::MAX).unwrap_or(1024);
        let affordable = descriptors.saturating_sub(RESERVED_DESCRIPTORS).max(8);
        let max_connections = configured.min(usize::try_from(affordable).unwrap_or(usize::MAX));
        if max_connections < configured {
            tracing::warn!(
                configured,
                max_connections,
                open_file_limit = descriptors,
                "--max-connections lowered to fit the open-file limit"
            );
        }
        let max_per_address = per_address.min(max_connections);
        ConnectionLimits { max_connections, max_per_address, header_read_timeout }
    }
}

/// Serves `app` on `listener` until `shutdown` is cancelled, then stops accepting, asks every
/// connection to finish its request in flight, and waits for them (the caller bounds the wait).
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnectionLimits,
    shutdown: CancellationToken,
) -> io::Result<()> {
    let slots = Arc::new(Semaphore::new(limits.max_connections));
    let graceful = GracefulShutdown::new();
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder.http1().timer(TokioTimer::new()).header_read_timeout(limits.header_read_timeout);
    builder.http2().timer(TokioTimer::new());
    let shedders = Arc::new(Semaphore::new(SHED_AT_ONCE));
    let addresses = PerAddress::new(limits.max_per_address);
    loop {
        let slot = match slots.clone().try_acquire_owned() {
            Ok(slot) => slot,
            // Every slot is taken: answer 503 to the newcomer at once rather than leave it in
            // the backlog behind clients that hold their connections open.
            Err(_) if shedders.available_permits() > 0 => {
                tokio::select! {
                    accepted = listener.accept() => match accepted {
                        Ok((stream, _)) => shed(stream, shedders.clone(), SHED_BODY),
                        Err(e) => accept_failed(&e).await,
                    },
                    () = shutdown.cancelled() => break,
                }
                continue;
            }
            Err(_) => tokio::select! {
                slot = slots.clone().acquire_owned() => slot.expect("the semaphore is never closed"),
                () = shutdown.cancelled() => break,
            },
        };
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    accept_failed(&e).await;
                    continue;
                }
            },
            () = shutdown.cancelled() => break,
        };
        let Some(address_slot) = addresses.take(peer.ip()) else {
            // The global slot goes back at once; the newcomer is told why.
            drop(slot);
            shed(stream, shedders.clone(), SHED_ADDRESS_BODY);
            continue;
        };
        // Small responses (/act) go out at once instead of waiting for Nagle's timer.
        let _ = stream.set_nodelay(true);
        let (builder, app, watcher) = (builder.clone(), app.clone(), graceful.watcher());
        let (header_timeout, shutdown) = (limits.header_read_timeout, shutdown.clone());
        tokio::spawn(async move {
            // hyper's header deadline starts once it knows the protocol, which it learns from
            // the first bytes: a connection that sends none is bounded here.
            if first_byte(&stream, header_timeout, &shutdown).await {
                let service = TowerToHyperService::new(app);
                let connection =
                    builder.serve_connection_with_upgrades(TokioIo::new(stream), service);
                // A client that goes away or breaks the protocol is its own problem, not an
                // error of the service: nothing to report beyond the request's own trace.
                if let Err(e) = watcher.watch(connection.into_owned()).await {
                    tracing::debug!(error = %e, "connection ended with an error");
                }
            }
            drop((slot, address_slot));
        });
    }
    drop(listener);
    graceful.shutdown().await;
    Ok(())
}

/// Connections answered 503 at once while every slot is taken; past this many, newcomers wait
/// in the listen backlog (each costs a descriptor, within [`RESERVED_DESCRIPTORS`]).
const SHED_AT_ONCE: usize = 32;

/// The body of the answer to a connection beyond the cap.
const SHED_BODY: &str = "{\"error\":{\"code\":\"too_many_connections\",\"message\":\"every \
    connection slot is taken (--max-connections); retry shortly\"}}";

/// The body of the answer to a connection beyond the per-address cap.
const SHED_ADDRESS_BODY: &str = "{\"error\":{\"code\":\"too_many_connections_from_address\",\
    \"message\":\"this address holds as many connections as one address may \
    (--max-connections-per-address); close one or retry shortly\"}}";

/// Open connections per client address, capped; a [`AddressSlot`] gives its place back when
/// dropped. A mutex over a map: taken once per accepted connection and once per close.
#[derive(Clone)]
struct PerAddress {
    open: Arc<std::sync::Mutex<std::collections::HashMap<std::net::IpAddr, usize>>>,
    max: usize,
}

impl PerAddress {
    fn new(max: usize) -> Self {
        PerAddress { open: Arc::default(), max }
    }

    /// A place for one more connection from `ip`, unless it holds `max` already.
    fn take(&self, ip: std::net::IpAddr) -> Option<AddressSlot> {
        let mut open = self.open.lock().expect("per-address lock");
        let count = open.entry(ip).or_insert(0);
        if *count >= self.max {
            return None;
        }
        *count += 1;
        Some(AddressSlot { addresses: self.clone(), ip })
    }
}

struct AddressSlot {
    addresses: PerAddress,
    ip: std::net::IpAddr,
}

impl Drop for AddressSlot {
    fn drop(&mut self) {
        let mut open = self.addresses.open.lock().expect("per-address lock");
        if let Some(count) = open.get_mut(&self.ip) {
            *count -= 1;
            // Forgotten once closed, so the map holds only addresses with open connections.
            if *count == 0 {
                open.remove(&self.ip);
            }
        }
    }
}

/// Writes a 503 with `body` to a connection beyond a cap and closes it (within a second),
/// holding one of the [`SHED_AT_ONCE`] permits meanwhile.
fn shed(stream: TcpStream, shedders: Arc<Semaphore>, body: &'static str) {
    use tokio::io::AsyncWriteExt;
    let Ok(permit) = shedders.try_acquire_owned() else { return };
    tokio::spawn(async move {
        let mut stream = stream;
        let response = format!(
            "HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n\
             Retry-After: 1\r\nConnection: close\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        );
        let answer = async {
            // The request's headers first: an HTTP client takes an answer that comes before
            // its request as a broken connection, not as a 503 to retry.
            read_headers(&mut stream).await?;
            stream.write_all(response.as_bytes()).await?;
            stream.shutdown().await
        };
        let _ = tokio::time::timeout(Duration::from_secs(2), answer).await;
        drop(permit);
    });
}

/// Reads (and drops) a request's head, up to its blank line or 16 KiB.
async fn read_headers(stream: &mut TcpStream) -> io::Result<()> {
    use tokio::io::AsyncReadExt;
    let mut head = Vec::new();
    let mut chunk = [0u8; 1024];
    while head.len() < 16 << 10 && !head.windows(4).any(|w| w == b"\r\n\r\n") {
        let n = stream.read(&mut chunk).await?;
        if n == 0 {
            break;
        }
        head.extend_from_slice(&chunk[..n]);
    }
    Ok(())
}

/// Whether the client sent something within `limit` (and before a shutdown began).
async fn first_byte(stream: &TcpStream, limit: Duration, shutdown: &CancellationToken) -> bool {
    let mut byte = [0u8; 1];
    tokio::select! {
        peeked = tokio::time::timeout(limit, stream.peek(&mut byte)) => {
            matches!(peeked, Ok(Ok(n)) if n > 0)
        }
        () = shutdown.cancelled() => false,
    }
}

/// Accept errors are about one connection (reset before accept) or a passing shortage of
/// descriptors: never a reason to stop serving.
async fn accept_failed(error: &io::Error) {
    if matches!(error.raw_os_error(), Some(EMFILE | ENFILE)) {
        tracing::warn!(error = %error, "out of file descriptors; pausing accept");
        tokio::time::sleep(ACCEPT_BACKOFF).await;
    } else {
        tracing::debug!(error = %error, "accept failed");
    }
}

/// A request body that ends in [`BodyTooSlow`] once, past `grace`, it has averaged fewer than
/// `min_rate` bytes per second since it began.
pub(crate) fn at_least(body: axum::body::Body, grace: Duration, min_rate: u64) -> axum::body::Body {
    use futures::StreamExt;
    let started = std::time::Instant::now();
    let mut received: u64 = 0;
    let paced = body.into_data_stream().map(move |chunk| {
        let chunk = chunk.map_err(axum::BoxError::from)?;
        received += chunk.len() as u64;
        let elapsed = started.elapsed();
        if let Some(late) = elapsed.checked_sub(grace) {
            if (received as f64) < min_rate as f64 * late.as_secs_f64() {
                return Err(BodyTooSlow { min_rate }.into());
            }
        }
        Ok::<_, axum::BoxError>(chunk)
    });
    axum::body::Body::from_stream(paced)
}

/// A request body that arrived slower than `--min-body-rate` on average.
#[derive(Debug, thiserror::Error)]
#[error("the request body arrived slower than {min_rate} bytes/s on average")]
pub struct BodyTooSlow {
    pub min_rate: u64,
}
