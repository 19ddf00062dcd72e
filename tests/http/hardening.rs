//! Regression tests of the hardening issue, each through the real server: crafted uploads stay
//! within bounded memory and get short answers, slow or idle clients are cut off, a closed log
//! pipe neither stops the service nor its shutdown, and out-of-range inputs get 400/422.

use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpStream};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::support::app::{assert_error, TestApp};
use reqwest::StatusCode;

/// Longest any liveness wait below lasts before the test gives up (a bound, not a timing claim).
const PATIENCE: Duration = Duration::from_secs(60);

/// A `safedice serve` child process on a free port, its stdout a pipe the test controls.
struct ServerProcess {
    child: Child,
    base_url: String,
}

impl ServerProcess {
    async fn start(data_dir: &Path, extra: &[&str]) -> ServerProcess {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new(env!("CARGO_BIN_EXE_safedice"))
            .args(["serve", "--bind", &format!("127.0.0.1:{port}"), "--data-dir"])
            .arg(data_dir)
            .args(extra)
            .env("RUST_LOG", "info")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start safedice serve");
        let server = ServerProcess { child, base_url: format!("http://127.0.0.1:{port}") };
        let started = Instant::now();
        while reqwest::get(server.url("/healthz")).await.is_err() {
            assert!(started.elapsed() < PATIENCE, "server did not come up");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        server
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base_url)
    }

    /// The peak resident set size so far (VmHWM), in bytes.
    fn peak_rss(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap();
        let line = status.lines().find(|l| l.starts_with("VmHWM:")).expect("VmHWM line");
        let kib: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
        kib * 1024
    }

    fn terminate(&self) {
        let pid = self.child.id().to_string();
        assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
    }

    /// Waits for the process to exit by itself; `None` if it is still running after PATIENCE.
    async fn wait_for_exit(&mut self) -> Option<std::process::ExitStatus> {
        let started = Instant::now();
        while started.elapsed() < PATIENCE {
            if let Some(status) = self.child.try_wait().unwrap() {
                return Some(status);
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        None
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An NPZ archive whose `observations.npy` (deflated) declares a `header_len`-byte header and
/// holds that many spaces: tiny compressed, huge if a parser believes it.
fn npy_header_bomb(header_len: u32) -> Vec<u8> {
    let mut npy = b"\x93NUMPY\x02\x00".to_vec();
    npy.extend_from_slice(&header_len.to_le_bytes());
    npy.resize(npy.len() + header_len as usize, b' ');
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options =
        zip::write::FileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    zip.start_file("observations.npy", options).unwrap();
    zip.write_all(&npy).unwrap();
    zip.finish().unwrap().into_inner()
}

#[tokio::test]
async fn an_npy_header_length_bomb_gets_a_short_422_within_bounded_memory() {
    let data_dir = tempfile::tempdir().unwrap();
    let server = ServerProcess::start(data_dir.path(), &[]).await;
    let baseline = server.peak_rss();
    let bomb = npy_header_bomb(128 << 20);
    assert!(bomb.len() < 1 << 20, "the bomb is {} bytes compressed", bomb.len());
    let form = reqwest::multipart::Form::new()
        .part("file", reqwest::multipart::Part::bytes(bomb).file_name("bomb.npz"));
    let response = reqwest::Client::new()
        .post(server.url("/v1/datasets"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::UNPROCESSABLE_ENTITY);
    let body = response.bytes().await.unwrap();
    assert!(body.len() < 2048, "a {}-byte answer", body.len());
    let body: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(body["error"]["code"], "invalid_dataset");
    let message = body["error"]["message"].as_str().unwrap();
    assert!(message.contains("header declares 134217728 bytes"), "{message}");
    // The 128 MiB header was never allocated (before the fix it cost ~1 GB of RSS).
    let grown = server.peak_rss().saturating_sub(baseline);
    assert!(grown < 64 << 20, "peak RSS grew by {grown} bytes");
    let datasets = reqwest::get(server.url("/v1/datasets")).await.unwrap();
    let listed: serde_json::Value = datasets.json().await.unwrap();
    assert_eq!(listed["total"], 0, "{listed}");
}

#[tokio::test]
async fn an_npz_entry_declaring_more_than_the_budget_is_refused_before_reading() {
    let app = TestApp::spawn().await;
    // An entry whose central directory says 4 GiB: refused from the declaration alone.
    // (0xFFFFFFFF itself means "see the zip64 field", hence one less.)
    let mut archive = npy_header_bomb(64);
    let name_at = archive.windows(16).rposition(|w| w == b"observations.npy").unwrap();
    // Central directory record: the uncompressed size sits 22 bytes before the 46-byte header's
    // end, i.e. at offset 24 of the record, which starts 46 bytes before the name.
    let record = name_at - 46;
    assert_eq!(&archive[record..record + 4], b"PK\x01\x02");
    archive[record + 24..record + 28].copy_from_slice(&(u32::MAX - 1).to_le_bytes());
    let response = app.upload_dataset("declared.npz", archive, None).await;
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_dataset").await;
    assert!(message.contains("declares 4294967294 bytes uncompressed"), "{message}");
    app.assert_no_datasets_stored().await;
}

#[tokio::test]
async fn an_npy_shape_whose_size_overflows_is_a_422() {
    let app = TestApp::spawn().await;
    let mut header =
        b"{'descr': '<f4', 'fortran_order': False, 'shape': (4294967296, 4294967296), }".to_vec();
    header.resize(118, b' ');
    header.push(b'\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend_from_slice(&(header.len() as u16).to_le_bytes());
    npy.extend_from_slice(&header);
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    zip.start_file("observations.npy", zip::write::FileOptions::default()).unwrap();
    zip.write_all(&npy).unwrap();
    let archive = zip.finish().unwrap().into_inner();
    let response = app.upload_dataset("overflow.npz", archive, None).await;
    let message = assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_dataset").await;
    assert!(message.contains("observations") && message.contains("overflows"), "{message}");
    app.assert_no_datasets_stored().await;
}

#[tokio::test]
async fn error_messages_quote_at_most_a_bounded_fragment_of_the_input() {
    let app = TestApp::spawn().await;
    let long = "x".repeat(5 << 20);
    let jsonl = format!(
        "{{\"episode\": 0, \"obs\": [0.0], \"action\": [0.5]}}\n{{\"episode\": \"{long}\", \"obs\": [0.0], \"action\": [0.5]}}\n"
    );
    let response = app.upload_dataset("long.jsonl", jsonl.into_bytes(), None).await;
    assert_eq!(response.status(), StatusCode::UNPROCESSABLE_ENTITY);
    let body = response.bytes().await.unwrap();
    assert!(body.len() <= 1200, "a {}-byte answer", body.len());
    let body: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert!(body["error"]["message"].as_str().unwrap().starts_with("line 2"), "{body}");
    app.assert_no_datasets_stored().await;

    let csv = format!("episode,obs_0,action_0\n0,{long},0.5\n");
    let response = app.upload_dataset("long.csv", csv.into_bytes(), None).await;
    assert_eq!(response.status(), StatusCode::UNPROCESSABLE_ENTITY);
    assert!(response.bytes().await.unwrap().len() <= 1200);

    // A JSON body whose unknown key is 5 MB long.
    let job = format!("{{\"{long}\": 1}}");
    let response = app
        .post("/v1/jobs")
        .header("content-type", "application/json")
        .body(job)
        .send()
        .await
        .unwrap();
    assert!(response.status().is_client_error(), "{}", response.status());
    assert!(response.bytes().await.unwrap().len() <= 1200);
    app.assert_no_datasets_stored().await;
    assert_eq!(app.count_rows("jobs").await, 0);
}

/// Writes `request` to a fresh connection and returns it.
fn connect(app: &TestApp, request: &[u8]) -> TcpStream {
    let mut stream = TcpStream::connect(app.addr).unwrap();
    stream.set_read_timeout(Some(PATIENCE)).unwrap();
    stream.write_all(request).unwrap();
    stream
}

/// Whether the server has already answered (or closed) this connection, without waiting.
fn was_answered(stream: &TcpStream) -> bool {
    stream.set_nonblocking(true).unwrap();
    let pending = matches!(stream.peek(&mut [0u8; 1]), Err(e) if e.kind() == ErrorKind::WouldBlock);
    stream.set_nonblocking(false).unwrap();
    !pending
}

/// Reads until the server closes the connection (or PATIENCE passes); what it sent.
fn read_until_closed(stream: &mut TcpStream) -> String {
    let mut received = Vec::new();
    let _ = stream.read_to_end(&mut received);
    String::from_utf8_lossy(&received).into_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_never_finishes_its_headers_is_disconnected() {
    let app = TestApp::spawn_with(|c| c.header_timeout_secs = 1).await;
    let mut stream = connect(&app, b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ");
    let started = Instant::now();
    let received =
        tokio::task::spawn_blocking(move || read_until_closed(&mut stream)).await.unwrap();
    assert!(started.elapsed() < PATIENCE, "the connection was never closed");
    assert!(!received.contains("200 OK"), "{received}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_upload_that_stalls_mid_body_gets_408_and_leaves_no_temp_file() {
    let app = TestApp::spawn_with(|c| c.body_idle_timeout_secs = 1).await;
    let head = "POST /v1/datasets HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XyZ\r\nContent-Length: 100000\r\n\r\n\
                --XyZ\r\nContent-Disposition: form-data; name=\"file\"; filename=\"d.jsonl\"\r\n\r\n\
                {\"episode\": 0, \"obs\": [0.0], \"action\": [0.5]}\n";
    let mut stream = connect(&app, head.as_bytes());
    let received =
        tokio::task::spawn_blocking(move || read_until_closed(&mut stream)).await.unwrap();
    assert!(received.starts_with("HTTP/1.1 408"), "{received}");
    assert!(received.contains("request_timeout"), "{received}");
    app.assert_no_datasets_stored().await;
}

/// An upload trickled a byte at a time never pauses past the idle timeout, so it is held to
/// an average rate instead: 408 `request_too_slow` soon after the grace period, nothing stored,
/// and its upload slot free again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_upload_trickled_a_byte_at_a_time_gets_408_and_frees_its_slot() {
    let app = TestApp::spawn_with(|c| {
        c.body_idle_timeout_secs = 1;
        c.min_body_rate = 1000;
        c.max_concurrent_uploads = 1;
    })
    .await;
    let head = "POST /v1/datasets HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XyZ\r\nContent-Length: 100000\r\n\r\n\
                --XyZ\r\nContent-Disposition: form-data; name=\"file\"; filename=\"d.jsonl\"\r\n\r\n";
    let mut stream = connect(&app, head.as_bytes());
    let started = Instant::now();
    let received = tokio::task::spawn_blocking(move || {
        while started.elapsed() < PATIENCE && !was_answered(&stream) {
            if stream.write_all(b" ").is_err() {
                break;
            }
            std::thread::sleep(Duration::from_millis(300));
        }
        read_until_closed(&mut stream)
    })
    .await
    .unwrap();
    assert!(received.starts_with("HTTP/1.1 408"), "{received}");
    assert!(received.contains("request_too_slow"), "{received}");
    eprintln!("answered after {:?}", started.elapsed());
    app.assert_no_datasets_stored().await;
    // The one upload slot is free: a real upload goes through.
    let (unlabeled, _) = crate::support::jobs::grid_datasets();
    crate::support::jobs::upload(&app.client, &app.base_url, &unlabeled, "after").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_upload_the_client_abandons_counts_as_499_not_as_a_server_error() {
    let app = TestApp::spawn().await;
    let head = "POST /v1/datasets HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XyZ\r\nContent-Length: 100000\r\n\r\n\
                --XyZ\r\nContent-Disposition: form-data; name=\"file\"; filename=\"d.jsonl\"\r\n\r\n\
                {\"episode\": 0, \"obs\": [0.0], \"action\": [0.5]}\n";
    let stream = connect(&app, head.as_bytes());
    // The client goes away mid-body.
    stream.shutdown(Shutdown::Both).unwrap();
    drop(stream);
    let abandoned =
        r#"safedice_http_requests_total{method="POST",route="/v1/datasets",status="499"} 1"#;
    let started = Instant::now();
    let metrics = loop {
        let text = app.get("/metrics").send().await.unwrap().text().await.unwrap();
        if text.contains(abandoned) || started.elapsed() > PATIENCE {
            break text;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert!(metrics.contains(abandoned), "{metrics}");
    assert!(!metrics.contains(r#"route="/v1/datasets",status="500""#), "{metrics}");
    app.assert_no_datasets_stored().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_declared_oversized_upload_is_answered_413_before_its_body_is_sent() {
    let app = TestApp::spawn_with(|c| c.max_upload_bytes = 1 << 20).await;
    let head = "POST /v1/datasets HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XyZ\r\n\
                Content-Length: 10000000000\r\n\r\n";
    let mut stream = connect(&app, head.as_bytes());
    // Not a byte of the body is sent: the answer must come anyway.
    let received =
        tokio::task::spawn_blocking(move || read_until_closed(&mut stream)).await.unwrap();
    assert!(received.starts_with("HTTP/1.1 413"), "{received}");
    assert!(received.to_ascii_lowercase().contains("connection: close"), "{received}");
    app.assert_no_datasets_stored().await;
}

/// Two transitions of one episode: a dataset the server stores.
const VALID_JSONL: &[u8] = b"{\"episode\": 0, \"obs\": [0.0, 0.1], \"action\": [0.5]}\n\
    {\"episode\": 0, \"obs\": [0.1, 0.2], \"action\": [-0.2], \"terminal\": true}\n";

/// One client holds at most half of the upload slots: with 2, a client whose upload is in
/// flight gets 503 `too_many_uploads_from_address` for a second one, and nothing of it is
/// stored, while an upload from another address goes through.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_client_holds_at_most_half_of_the_upload_slots() {
    let app = TestApp::spawn_with(|c| {
        c.max_concurrent_uploads = 2;
        c.body_idle_timeout_secs = 30;
    })
    .await;
    let head = "POST /v1/datasets HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XyZ\r\nContent-Length: 100000\r\n\r\n\
                --XyZ\r\nContent-Disposition: form-data; name=\"file\"; filename=\"d.jsonl\"\r\n\r\n";
    let mut slow = connect(&app, head.as_bytes());
    // The paused upload holds its client's one slot once its handler runs; until then a second
    // upload from the same address may go through (and is stored), or win the slot so that the
    // paused one is the upload refused (reopen it then), so look until one is refused.
    let (mut refused, mut stored_before) = (None, 0);
    let started = Instant::now();
    while started.elapsed() < PATIENCE {
        stored_before = app.count_rows("datasets").await;
        let response = app.upload_dataset("d.jsonl", VALID_JSONL.to_vec(), None).await;
        if response.status() == StatusCode::SERVICE_UNAVAILABLE {
            refused = Some(response);
            break;
        }
        assert!(response.status().is_success(), "{}", response.status());
        if was_answered(&slow) {
            slow = connect(&app, head.as_bytes());
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let response = refused.expect("the client's second upload was never refused");
    assert_eq!(response.headers()["retry-after"], "1");
    assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "too_many_uploads_from_address").await;
    assert_eq!(app.count_rows("datasets").await, stored_before, "nothing of it was stored");
    let other = reqwest::Client::builder()
        .local_address("127.0.0.2".parse::<std::net::IpAddr>().unwrap())
        .build()
        .unwrap();
    let form = reqwest::multipart::Form::new()
        .part("file", reqwest::multipart::Part::bytes(VALID_JSONL.to_vec()).file_name("d.jsonl"));
    let response = other.post(app.url("/v1/datasets")).multipart(form).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::CREATED, "another address has the other slot");
    slow.shutdown(Shutdown::Both).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_beyond_the_concurrency_cap_get_503_with_retry_after() {
    let app = TestApp::spawn_with(|c| {
        c.max_concurrent_uploads = 1;
        c.body_idle_timeout_secs = 30;
    })
    .await;
    // One upload in flight, its body paused.
    let head = "POST /v1/datasets HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XyZ\r\nContent-Length: 100000\r\n\r\n\
                --XyZ\r\nContent-Disposition: form-data; name=\"file\"; filename=\"d.jsonl\"\r\n\r\n";
    let mut slow = connect(&app, head.as_bytes());
    let mut second = None;
    let started = Instant::now();
    // The first upload holds the only permit once its handler runs; until then a second upload
    // may win it, and the paused one is the upload refused. Retry (reopening the paused upload
    // when it was the one answered) until the cap is seen.
    while started.elapsed() < PATIENCE {
        let response = app.upload_dataset("d.jsonl", b"{}\n".to_vec(), None).await;
        if response.status() == StatusCode::SERVICE_UNAVAILABLE {
            second = Some(response);
            break;
        }
        if was_answered(&slow) {
            slow = connect(&app, head.as_bytes());
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let response = second.expect("the second concurrent upload was never refused");
    assert_eq!(response.headers()["retry-after"], "1");
    assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "too_many_uploads").await;
    slow.shutdown(Shutdown::Both).unwrap();
    // With the first one gone, uploads go through again.
    let started = Instant::now();
    loop {
        let response = app.upload_dataset("d.jsonl", b"{}\n".to_vec(), None).await;
        if response.status() != StatusCode::SERVICE_UNAVAILABLE {
            assert_eq!(response.status(), StatusCode::UNPROCESSABLE_ENTITY);
            break;
        }
        assert!(started.elapsed() < PATIENCE, "the permit was never released");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    app.assert_no_datasets_stored().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_beyond_the_cap_do_not_lock_out_healthz() {
    let app = TestApp::spawn_with(|c| {
        c.max_connections = 4;
        c.header_timeout_secs = 1;
    })
    .await;
    // Twice the cap of connections that never send a byte.
    let idle: Vec<TcpStream> = (0..8).map(|_| TcpStream::connect(app.addr).unwrap()).collect();
    let client = reqwest::Client::builder().timeout(PATIENCE).build().unwrap();
    // While the slots are taken a newcomer is told so at once (503 with Retry-After) instead of
    // waiting in the backlog; once the idle ones are dropped at the header deadline it is served.
    let started = Instant::now();
    loop {
        let response = client.get(app.url("/healthz")).send().await.unwrap();
        if response.status() == StatusCode::OK {
            break;
        }
        assert_eq!(response.headers()["retry-after"], "1");
        assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "too_many_connections").await;
        assert!(started.elapsed() < PATIENCE, "never served");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    drop(idle);
}

/// Clients holding every slot with keep-alive requests (a /healthz or a 401 now and then) do
/// not make newcomers time out: a 401 closes its connection, and a newcomer beyond the cap gets
/// a prompt 503 it can retry.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_held_by_keep_alive_clients_shed_newcomers_at_once() {
    let app = TestApp::spawn_with(|c| {
        c.max_connections = 2;
        c.api_token = Some("secret".into());
    })
    .await;
    // A 401 answers and closes: the slot is free again.
    let mut unauthorized = connect(&app, b"GET /v1/jobs HTTP/1.1\r\nHost: x\r\n\r\n");
    let received =
        tokio::task::spawn_blocking(move || read_until_closed(&mut unauthorized)).await.unwrap();
    assert!(received.starts_with("HTTP/1.1 401"), "{received}");
    assert!(received.to_lowercase().contains("connection: close"), "{received}");
    // Two keep-alive clients take both slots.
    let holders: Vec<TcpStream> = (0..2)
        .map(|_| {
            let mut stream = connect(&app, b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n");
            let mut answer = [0u8; 12];
            stream.read_exact(&mut answer).unwrap();
            assert_eq!(&answer, b"HTTP/1.1 200");
            stream
        })
        .collect();
    let started = Instant::now();
    let response = reqwest::get(app.url("/healthz")).await.unwrap();
    assert!(started.elapsed() < Duration::from_secs(2), "answered at once, not after a timeout");
    assert_error(response, StatusCode::SERVICE_UNAVAILABLE, "too_many_connections").await;
    drop(holders);
}

/// REST's and gRPC's listeners share one connection budget: with REST holding every slot, a
/// connection to the gRPC port is shed at once too, and served once a REST slot is free.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_grpc_listener_counts_against_the_same_connection_cap() {
    let app = TestApp::spawn_with(|c| {
        c.max_connections = 2;
        c.grpc_bind = Some("127.0.0.1:0".parse().unwrap());
    })
    .await;
    let grpc = app.grpc_addr.expect("the gRPC listener");
    let mut holders: Vec<TcpStream> = (0..2)
        .map(|_| {
            let mut stream = connect(&app, b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n");
            let mut answer = [0u8; 12];
            stream.read_exact(&mut answer).unwrap();
            assert_eq!(&answer, b"HTTP/1.1 200");
            stream
        })
        .collect();
    let mut newcomer = TcpStream::connect(grpc).unwrap();
    newcomer.set_read_timeout(Some(PATIENCE)).unwrap();
    // A gRPC client opens with HTTP/2's preface; the shed answer waits for a request's head.
    newcomer.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n").unwrap();
    let received =
        tokio::task::spawn_blocking(move || read_until_closed(&mut newcomer)).await.unwrap();
    assert!(received.starts_with("HTTP/1.1 503"), "shed on the gRPC port too: {received}");
    assert!(received.contains("too_many_connections"), "{received}");
    drop(holders.pop());
    // The freed slot serves the gRPC port: a connection there is held open, not shed.
    let started = Instant::now();
    loop {
        let stream = TcpStream::connect(grpc).unwrap();
        std::thread::sleep(Duration::from_millis(200));
        if !was_answered(&stream) {
            break;
        }
        assert!(started.elapsed() < PATIENCE, "the freed slot never served the gRPC port");
    }
}

/// One address holding its share of connections (`--max-connections-per-address`) gets a
/// prompt 503 for one more, while another address is served; a slot it closes is its own again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_address_cannot_take_more_than_its_share_of_connections() {
    let app = TestApp::spawn_with(|c| c.max_connections_per_address = 2).await;
    let healthz = b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n";
    let mut holders: Vec<TcpStream> = (0..2)
        .map(|_| {
            let mut stream = connect(&app, healthz);
            let mut answer = [0u8; 12];
            stream.read_exact(&mut answer).unwrap();
            assert_eq!(&answer, b"HTTP/1.1 200");
            stream
        })
        .collect();
    // A third connection from 127.0.0.1: answered at once and closed.
    let mut third = connect(&app, healthz);
    let received =
        tokio::task::spawn_blocking(move || read_until_closed(&mut third)).await.unwrap();
    assert!(received.starts_with("HTTP/1.1 503"), "{received}");
    assert!(received.contains("Retry-After: 1"), "{received}");
    let body: serde_json::Value =
        serde_json::from_str(received.split("\r\n\r\n").nth(1).unwrap()).unwrap();
    assert_eq!(body["error"]["code"], "too_many_connections_from_address", "{body}");
    // Another loopback address is served meanwhile.
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind("127.0.0.2:0".parse().unwrap()).unwrap();
    let mut other = socket.connect(app.addr).await.unwrap().into_std().unwrap();
    other.set_nonblocking(false).unwrap();
    other.set_read_timeout(Some(PATIENCE)).unwrap();
    other.write_all(healthz).unwrap();
    let mut answer = [0u8; 12];
    other.read_exact(&mut answer).unwrap();
    assert_eq!(&answer, b"HTTP/1.1 200");
    // 127.0.0.1 closes one of its two: a newcomer from it is served again.
    drop(holders.pop());
    let started = Instant::now();
    loop {
        let response = reqwest::get(app.url("/healthz")).await.unwrap();
        if response.status() == StatusCode::OK {
            break;
        }
        assert!(started.elapsed() < PATIENCE, "the closed slot never came back");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    drop((holders, other));
}

#[tokio::test]
async fn offsets_beyond_what_sql_can_count_are_refused() {
    let app = TestApp::spawn().await;
    for offset in ["9223372036854775808", "18446744073709551615"] {
        for list in ["/v1/datasets", "/v1/jobs", "/v1/policies"] {
            let response = app.get(&format!("{list}?offset={offset}")).send().await.unwrap();
            let message =
                assert_error(response, StatusCode::BAD_REQUEST, "invalid_pagination").await;
            assert!(message.contains("offset"), "{message}");
        }
    }
    let last = app.get("/v1/datasets?offset=9223372036854775807").send().await.unwrap();
    assert_eq!(last.status(), StatusCode::OK);
    let page: serde_json::Value = last.json().await.unwrap();
    assert_eq!(page["items"], serde_json::json!([]));
    assert_eq!(page["next_offset"], serde_json::Value::Null);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_closed_log_pipe_neither_stops_the_service_nor_its_shutdown() {
    let data_dir = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::start(data_dir.path(), &["--log-format", "json"]).await;
    // Whatever read the logs goes away (as `| head` does); every request logs a line.
    drop(server.child.stdout.take());
    drop(server.child.stderr.take());
    let client = reqwest::Client::new();
    for _ in 0..200 {
        let response = client.get(server.url("/healthz")).send().await.unwrap();
        assert_eq!(response.status(), StatusCode::OK);
    }
    let missing = client.get(server.url("/v1/datasets/nope")).send().await.unwrap();
    assert_eq!(missing.status(), StatusCode::NOT_FOUND);
    server.terminate();
    let status = server.wait_for_exit().await.expect("SIGTERM did not stop the server");
    assert!(status.success(), "{status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn logs_written_to_a_pipe_carry_no_terminal_colours() {
    let data_dir = tempfile::tempdir().unwrap();
    let mut server = ServerProcess::start(data_dir.path(), &["--log-format", "pretty"]).await;
    let _ = reqwest::get(server.url("/healthz")).await.unwrap();
    server.terminate();
    server.wait_for_exit().await.expect("SIGTERM did not stop the server");
    let mut logs = String::new();
    server.child.stdout.take().unwrap().read_to_string(&mut logs).unwrap();
    assert!(logs.contains("safedice listening"), "{logs}");
    assert!(!logs.contains('\u{1b}'), "ANSI escape codes in piped logs: {logs}");
}

/// Bodies are JSON objects whose keys each appear once: an array is not read as a struct by
/// position, and a repeated key is refused rather than the last one silently winning. Each is
/// a 422 `invalid_body` that stores nothing.
#[tokio::test]
async fn positional_arrays_and_repeated_keys_are_refused_and_change_nothing() {
    use crate::support::jobs::{create_job, grid_datasets, small_config, upload};
    let app = TestApp::spawn_with(|c| c.workers = 0).await;
    let u = upload(&app.client, &app.base_url, &grid_datasets().0, "grid").await;
    let body = serde_json::json!({"algorithm": "bc", "unlabeled_dataset": u, "name": "kept",
                                  "config": small_config(10, 0)});
    let job = create_job(&app.client, &app.base_url, body).await;
    let id = job["id"].as_str().unwrap();
    let send = |method: reqwest::Method, path: String, text: &'static str| {
        app.client
            .request(method, app.url(&path))
            .header("content-type", "application/json")
            .body(text)
            .send()
    };
    let refused = [
        (reqwest::Method::PATCH, format!("/v1/jobs/{id}"), "[null, null]", "must be a JSON object"),
        (
            reqwest::Method::PATCH,
            format!("/v1/jobs/{id}"),
            r#"{"name": "a", "name": null}"#,
            "`name` appears twice",
        ),
        (
            reqwest::Method::POST,
            "/v1/jobs".to_owned(),
            r#"{"algorithm": "bc", "algorithm": "bc"}"#,
            "appears twice",
        ),
        (reqwest::Method::POST, "/v1/jobs".to_owned(), r#"[["bc"]]"#, "must be a JSON object"),
        (
            reqwest::Method::POST,
            "/v1/policies/p/act".to_owned(),
            "[[[0.0]], true, 5]",
            "must be a JSON object",
        ),
        (
            reqwest::Method::POST,
            "/v1/policies/p/act".to_owned(),
            r#"{"observations": [[0.0]], "observations": [[1.0]]}"#,
            "duplicate field `observations`",
        ),
    ];
    for (method, path, text, expected) in refused {
        let response = send(method, path, text).await.unwrap();
        let message =
            assert_error(response, StatusCode::UNPROCESSABLE_ENTITY, "invalid_body").await;
        assert!(message.contains(expected), "{text}: {message}");
    }
    assert_eq!(app.count_rows("jobs").await, 1);
    let stored = app.get(&format!("/v1/jobs/{id}")).send().await.unwrap();
    assert_eq!(stored.json::<serde_json::Value>().await.unwrap()["name"], "kept");
}
