//! Accepting connections, with the limits that keep slow or idle clients from exhausting the
//! process: a cap on open connections (below the file-descriptor limit, so the database and
//! uploads always find descriptors), a deadline for a request's headers (slowloris; it also
//! closes keep-alive connections left idle that long), and a deadline between two pieces of a
//! request body (a body that trickles one byte per minute), a deadline for a response a client
//! stops reading ([`StallLimited`]), and a cap per client address (an IPv6 client's whole /64).
//! `axum::serve` has none of these knobs, so this is its loop on `hyper-util` with them set.

use std::io;
use std::sync::Arc;
use std::time::Duration;

use axum::http::Request;
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tower::ServiceExt;

use super::client_slots::Client;
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
    /// A write the client does not take within this closes the connection (None: no limit).
    pub send_stall_timeout: Option<Duration>,
}

impl ConnectionLimits {
    /// `configured`, lowered to what the process's open-file limit leaves after
    /// [`RESERVED_DESCRIPTORS`]. Raises the soft limit to the hard one first, as servers do.
    pub fn new(
        configured: usize,
        per_address: usize,
        header_read_timeout: Duration,
        send_stall_timeout: Option<Duration>,
    ) -> Self {
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
        ConnectionLimits {
            max_connections,
            max_per_address,
            header_read_timeout,
            send_stall_timeout,
        }
    }
}

/// The connection slots of [`ConnectionLimits`], shared by every listener of the process (the
/// REST and the gRPC one): the caps hold for the server, not per port.
#[derive(Clone)]
pub struct ConnectionSlots {
    slots: Arc<Semaphore>,
    addresses: PerAddress,
}

impl ConnectionSlots {
    pub fn new(limits: &ConnectionLimits) -> Self {
        ConnectionSlots {
            slots: Arc::new(Semaphore::new(limits.max_connections)),
            addresses: PerAddress::new(limits.max_per_address),
        }
    }
}

/// Serves `app` on `listener` until `shutdown` is cancelled, then stops accepting, asks every
/// connection to finish its request in flight, and waits for them (the caller bounds the wait).
/// Connections take their places from `budget`, which other listeners may share.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnectionLimits,
    budget: ConnectionSlots,
    shutdown: CancellationToken,
) -> io::Result<()> {
    let ConnectionSlots { slots, addresses } = budget;
    let graceful = GracefulShutdown::new();
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder.http1().timer(TokioTimer::new()).header_read_timeout(limits.header_read_timeout);
    builder.http2().timer(TokioTimer::new());
    let shedders = Arc::new(Semaphore::new(SHED_AT_ONCE));
    loop {
        // Accepted first, then given a slot: a listener waiting for connections holds none, so
        // listeners that share the slots (REST and gRPC) each get all of them.
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
        let slot = match slots.clone().try_acquire_owned() {
            Ok(slot) => slot,
            // Every slot is taken: answer 503 to the newcomer at once rather than leave it
            // waiting behind clients that hold their connections open.
            Err(_) if shedders.available_permits() > 0 => {
                shed(stream, shedders.clone(), SHED_BODY);
                continue;
            }
            // Too many answers in flight already: this one waits for a slot, and newcomers
            // wait in the listen backlog meanwhile (nothing accepts them).
            Err(_) => tokio::select! {
                slot = slots.clone().acquire_owned() => slot.expect("the semaphore is never closed"),
                () = shutdown.cancelled() => break,
            },
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
        let send_stall = limits.send_stall_timeout;
        let client = Client(client_of(peer.ip()));
        tokio::spawn(async move {
            // hyper's header deadline starts once it knows the protocol, which it learns from
            // the first bytes: a connection that sends none is bounded here.
            if first_byte(&stream, header_timeout, &shutdown).await {
                // Every request knows its client, for the slots it may hold a share of.
                let app = app.map_request(move |mut request: Request<Incoming>| {
                    request.extensions_mut().insert(client);
                    request
                });
                let service = TowerToHyperService::new(app);
                let io = TokioIo::new(StallLimited::new(stream, send_stall));
                let connection = builder.serve_connection_with_upgrades(io, service);
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

    /// A place for one more connection from `ip`, unless its client holds `max` already.
    fn take(&self, ip: std::net::IpAddr) -> Option<AddressSlot> {
        let ip = client_of(ip);
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

/// The client an address belongs to, as the per-address cap counts: an IPv4 address (also
/// when it arrives IPv4-mapped), or an IPv6 address's /64, which one client or site holds
/// whole (ISPs delegate at least a /64; a host picks any address in it, one per connection if
/// it likes).
fn client_of(ip: std::net::IpAddr) -> std::net::IpAddr {
    use std::net::{IpAddr, Ipv6Addr};
    match ip {
        IpAddr::V4(v4) => IpAddr::V4(v4),
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let prefix = u128::from(v6) & !((1u128 << 64) - 1);
                IpAddr::V6(Ipv6Addr::from(prefix))
            }
        },
    }
}

/// A connection whose writes may wait at most `limit` on a client that reads nothing: a
/// pending write that outlasts it fails with `TimedOut`, hyper drops the connection and with
/// it the response (and whatever it held). hyper has read deadlines but none for writes.
pub(crate) struct StallLimited<S> {
    inner: S,
    limit: Option<Duration>,
    /// Running while a write is pending; cleared by any write that goes through.
    stalled: Option<std::pin::Pin<Box<tokio::time::Sleep>>>,
}

impl<S> StallLimited<S> {
    pub(crate) fn new(inner: S, limit: Option<Duration>) -> Self {
        StallLimited { inner, limit, stalled: None }
    }

    /// `Pending` from the socket: starts the deadline, or fails once it has passed.
    fn pending<T>(&mut self, cx: &mut std::task::Context<'_>) -> std::task::Poll<io::Result<T>> {
        use std::task::Poll;
        let Some(limit) = self.limit else { return Poll::Pending };
        let sleep = self.stalled.get_or_insert_with(|| Box::pin(tokio::time::sleep(limit)));
        match std::future::Future::poll(sleep.as_mut(), cx) {
            Poll::Ready(()) => Poll::Ready(Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("the client read nothing for {limit:?} (--send-stall-timeout-secs)"),
            ))),
            Poll::Pending => Poll::Pending,
        }
    }

    fn settle<T>(
        &mut self,
        cx: &mut std::task::Context<'_>,
        polled: std::task::Poll<io::Result<T>>,
    ) -> std::task::Poll<io::Result<T>> {
        match polled {
            std::task::Poll::Pending => self.pending(cx),
            ready => {
                self.stalled = None;
                ready
            }
        }
    }
}

impl<S: tokio::io::AsyncRead + Unpin> tokio::io::AsyncRead for StallLimited<S> {
    fn poll_read(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<S: tokio::io::AsyncWrite + Unpin> tokio::io::AsyncWrite for StallLimited<S> {
    fn poll_write(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<io::Result<usize>> {
        let polled = std::pin::Pin::new(&mut self.inner).poll_write(cx, buf);
        self.settle(cx, polled)
    }

    fn poll_write_vectored(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> std::task::Poll<io::Result<usize>> {
        let polled = std::pin::Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        self.settle(cx, polled)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<io::Result<()>> {
        let polled = std::pin::Pin::new(&mut self.inner).poll_flush(cx);
        self.settle(cx, polled)
    }

    fn poll_shutdown(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_shutdown(cx)
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::IpAddr;

    /// One client per IPv4 address (mapped or not) and per IPv6 /64.
    #[test]
    fn an_ipv6_client_is_its_slash_64() {
        let client = |text: &str| client_of(text.parse::<IpAddr>().unwrap());
        assert_eq!(client("203.0.113.7"), client("::ffff:203.0.113.7"));
        assert_ne!(client("203.0.113.7"), client("203.0.113.8"));
        assert_eq!(client("2001:db8:1:2:aaaa::1"), client("2001:db8:1:2:ffff:ffff:ffff:fffe"));
        assert_eq!(client("2001:db8:1:2::9"), "2001:db8:1:2::".parse::<IpAddr>().unwrap());
        assert_ne!(client("2001:db8:1:2::1"), client("2001:db8:1:3::1"));
    }

    /// A write the peer never takes fails after the limit, and one that goes through resets it.
    #[tokio::test]
    async fn a_write_that_waits_past_the_limit_fails() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        // A pipe of 64 bytes: filled, then read from (the wait ends, the limit resets), filled
        // again, then never read.
        let (writer, mut reader) = tokio::io::duplex(64);
        let mut limited = StallLimited::new(writer, Some(Duration::from_millis(200)));
        limited.write_all(&[0u8; 64]).await.unwrap();
        let drain = tokio::spawn(async move {
            let mut half = [0u8; 32];
            reader.read_exact(&mut half).await.unwrap();
            reader
        });
        limited.write_all(&[1u8; 32]).await.unwrap();
        let _reader = drain.await.unwrap();
        let error = limited.write_all(&[2u8; 1]).await.unwrap_err();
        assert_eq!(error.kind(), io::ErrorKind::TimedOut);
        assert!(error.to_string().contains("--send-stall-timeout-secs"), "{error}");
    }
}
