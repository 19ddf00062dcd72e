//! Test harness shared by the HTTP tests: starts the real server (the same code path as
//! `safedice serve`) on a free loopback port with a fresh temp data directory, and talks HTTP
//! to it. Reusable by every resource's tests: `TestApp::spawn().await`, then `app.get(path)`.
//!
//! The store is SQLite in the data directory, or a fresh database of its own in the test
//! process's PostgreSQL cluster (`super::postgres`): the binary's `TEST_DATABASE`, overridden by
//! `SAFEDICE_TEST_DATABASE=sqlite|postgres` (which is how `tests/http/on_postgres.rs` runs the
//! HTTP tests again on PostgreSQL).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use reqwest::{RequestBuilder, Response, StatusCode};
use safedice::config::ServeConfig;
use safedice::server::Server;
use safedice::store::Store;
use sqlx::{AnyConnection, Connection};

/// A running server on its own data directory.
pub struct TestApp {
    /// `http://127.0.0.1:PORT`; changes on [`TestApp::restart`].
    pub base_url: String,
    pub addr: SocketAddr,
    /// The gRPC listener's address, when the configuration sets `grpc_bind`.
    pub grpc_addr: Option<SocketAddr>,
    pub client: reqwest::Client,
    /// The configuration it runs with (port 0; edit it and restart to change settings).
    pub config: ServeConfig,
    data_dir: tempfile::TempDir,
    server: Option<Server>,
}

impl TestApp {
    /// A server with the default settings (no token, loopback).
    pub async fn spawn() -> TestApp {
        Self::spawn_with(|_| {}).await
    }

    /// A server whose settings `configure` adjusts (tokens, upload limit, CORS...).
    pub async fn spawn_with(configure: impl FnOnce(&mut ServeConfig)) -> TestApp {
        let data_dir = tempfile::tempdir().expect("temp data dir");
        let mut config = ServeConfig::new(data_dir.path());
        config.bind = "127.0.0.1:0".parse().unwrap();
        config.database_url = test_database_url().await;
        configure(&mut config);
        let server = Server::start(config.clone()).await.expect("server starts");
        let addr = server.local_addr();
        TestApp {
            base_url: format!("http://{addr}"),
            addr,
            grpc_addr: server.grpc_addr(),
            client: reqwest::Client::new(),
            config,
            data_dir,
            server: Some(server),
        }
    }

    pub fn data_dir(&self) -> &Path {
        self.data_dir.path()
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base_url)
    }

    /// A request carrying the API token when the server has one.
    pub fn request(&self, method: reqwest::Method, path: &str) -> RequestBuilder {
        let builder = self.client.request(method, self.url(path));
        match &self.config.api_token {
            Some(token) => builder.bearer_auth(token),
            None => builder,
        }
    }

    pub fn get(&self, path: &str) -> RequestBuilder {
        self.request(reqwest::Method::GET, path)
    }

    pub fn post(&self, path: &str) -> RequestBuilder {
        self.request(reqwest::Method::POST, path)
    }

    pub fn delete(&self, path: &str) -> RequestBuilder {
        self.request(reqwest::Method::DELETE, path)
    }

    /// Uploads `contents` as a dataset file named `file_name` (multipart `file` field), with an
    /// optional `name` field.
    pub async fn upload_dataset(
        &self,
        file_name: &str,
        contents: Vec<u8>,
        name: Option<&str>,
    ) -> Response {
        let mut form = reqwest::multipart::Form::new().part(
            "file",
            reqwest::multipart::Part::bytes(contents).file_name(file_name.to_owned()),
        );
        if let Some(name) = name {
            form = form.text("name", name.to_owned());
        }
        self.post("/v1/datasets").multipart(form).send().await.expect("upload request")
    }

    /// Uploads a dataset and returns its id, panicking unless the server answers 201.
    pub async fn create_dataset(&self, file_name: &str, contents: Vec<u8>) -> String {
        let response = self.upload_dataset(file_name, contents, None).await;
        assert_eq!(response.status(), StatusCode::CREATED, "upload of {file_name} failed");
        let body: serde_json::Value = response.json().await.unwrap();
        body["id"].as_str().unwrap().to_owned()
    }

    /// Asserts that no dataset is stored: no row, no canonical file, no temp upload left.
    pub async fn assert_no_datasets_stored(&self) {
        assert_eq!(self.count_rows("datasets").await, 0, "a dataset row was stored");
        assert_eq!(self.files_in("datasets"), Vec::<PathBuf>::new(), "a dataset file was stored");
        assert_eq!(self.stored_dataset_bytes().await, 0, "dataset bytes were stored");
        assert_eq!(self.files_in("tmp"), Vec::<PathBuf>::new(), "a temp upload was left behind");
    }

    /// Graceful shutdown; the data directory stays.
    pub async fn stop(&mut self) {
        if let Some(server) = self.server.take() {
            server.stop().await.expect("server stops cleanly");
        }
    }

    /// Stops (if running) and starts again on the same data directory with `self.config`.
    pub async fn restart(&mut self) {
        self.stop().await;
        let server = Server::start(self.config.clone()).await.expect("server restarts");
        self.addr = server.local_addr();
        self.grpc_addr = server.grpc_addr();
        self.base_url = format!("http://{}", self.addr);
        self.server = Some(server);
    }

    /// Whether this server's store is PostgreSQL.
    pub fn is_postgres(&self) -> bool {
        self.config.database_url.is_some()
    }

    /// For the tests of what only the SQLite store has (files in the data directory): true, and
    /// says so, on PostgreSQL.
    pub fn skip_on_postgres(&self, why: &str) -> bool {
        if self.is_postgres() {
            eprintln!("skipped on PostgreSQL: {why}");
        }
        self.is_postgres()
    }

    /// A direct connection to the server's database, to check what was (not) stored. Queries
    /// take `$1`-style parameters, which both backends read.
    pub async fn db(&self) -> AnyConnection {
        sqlx::any::install_default_drivers();
        let url = match &self.config.database_url {
            Some(url) => url.clone(),
            None => format!("sqlite://{}", self.data_dir().join("safedice.sqlite").display()),
        };
        AnyConnection::connect(&url).await.expect("open the test database")
    }

    /// The server's store, opened beside it.
    pub async fn store(&self) -> Store {
        Store::connect(self.data_dir(), self.config.database_url.as_deref())
            .await
            .expect("open the store")
    }

    /// How many datasets have their bytes stored: files on SQLite, chunked rows on PostgreSQL.
    pub async fn stored_dataset_bytes(&self) -> usize {
        if !self.is_postgres() {
            return self.files_in("datasets").len();
        }
        let mut db = self.db().await;
        let count: i64 =
            sqlx::query_scalar("SELECT COUNT(DISTINCT dataset_id) FROM dataset_chunks")
                .fetch_one(&mut db)
                .await
                .expect("count dataset chunks");
        count as usize
    }

    pub async fn count_rows(&self, table: &str) -> i64 {
        let mut db = self.db().await;
        let count = sqlx::query_scalar(&format!("SELECT COUNT(*) FROM {table}"))
            .fetch_one(&mut db)
            .await
            .expect("count rows");
        db.close().await.unwrap();
        count
    }

    /// Rows of `table` whose `column` is `value`.
    pub async fn count_where(&self, table: &str, column: &str, value: &str) -> i64 {
        let mut db = self.db().await;
        let count =
            sqlx::query_scalar(&format!("SELECT COUNT(*) FROM {table} WHERE {column} = $1"))
                .bind(value)
                .fetch_one(&mut db)
                .await
                .expect("count rows");
        db.close().await.unwrap();
        count
    }

    /// Files (not directories) under `sub` of the data directory, sorted.
    pub fn files_in(&self, sub: &str) -> Vec<PathBuf> {
        let mut files: Vec<PathBuf> = std::fs::read_dir(self.data_dir().join(sub))
            .map(|entries| entries.map(|e| e.unwrap().path()).filter(|p| p.is_file()).collect())
            .unwrap_or_default();
        files.sort();
        files
    }

    /// Inserts a job row directly (the jobs API arrives with the job runner).
    pub async fn insert_job(
        &self,
        id: &str,
        status: &str,
        unlabeled: &str,
        non_preferred: Option<&str>,
    ) {
        let mut db = self.db().await;
        sqlx::query(
            "INSERT INTO jobs (id, algorithm, status, unlabeled_dataset_id, \
             non_preferred_dataset_id, created_at, updated_at) \
             VALUES ($1, 'safedice', $2, $3, $4, '2026-01-01T00:00:00Z', '2026-01-01T00:00:00Z')",
        )
        .bind(id)
        .bind(status)
        .bind(unlabeled)
        .bind(non_preferred)
        .execute(&mut db)
        .await
        .expect("insert a job row");
        db.close().await.unwrap();
    }
}

/// The database a new test server uses: None for SQLite in its data directory. PostgreSQL
/// without its binaries falls back to SQLite (the cluster support has said so loudly, or failed
/// the test where PostgreSQL is required).
async fn test_database_url() -> Option<String> {
    let chosen = std::env::var("SAFEDICE_TEST_DATABASE");
    match chosen.as_deref().unwrap_or(crate::TEST_DATABASE) {
        "postgres" => match super::postgres::cluster() {
            Some(cluster) => Some(cluster.new_database().await),
            None => None,
        },
        "sqlite" => None,
        other => panic!("SAFEDICE_TEST_DATABASE={other}: expected sqlite or postgres"),
    }
}

impl Drop for TestApp {
    fn drop(&mut self) {
        if let Some(server) = &self.server {
            server.shutdown_token().cancel();
        }
    }
}

/// Asserts an error response: its status and the `{"error": {"code", "message"}}` body; returns
/// the message.
pub async fn assert_error(response: Response, status: StatusCode, code: &str) -> String {
    assert_eq!(response.status(), status, "unexpected status for {}", response.url());
    let body: serde_json::Value = response.json().await.expect("error body is JSON");
    assert_eq!(body["error"]["code"], code, "unexpected error body {body}");
    let message = body["error"]["message"].as_str().expect("error message is a string");
    assert!(!message.is_empty(), "empty error message");
    assert_eq!(body.as_object().unwrap().len(), 1, "extra top-level fields in {body}");
    message.to_owned()
}

/// Asserts an Open Inference Protocol error (`/v2`): its status and the protocol's body
/// `{"error": "message"}`; returns the message.
pub async fn assert_v2_error(response: Response, status: StatusCode) -> String {
    assert_eq!(response.status(), status, "unexpected status for {}", response.url());
    let body: serde_json::Value = response.json().await.expect("error body is JSON");
    let message = body["error"].as_str().unwrap_or_else(|| panic!("not a v2 error: {body}"));
    assert!(!message.is_empty(), "empty error message");
    assert_eq!(body.as_object().unwrap().len(), 1, "extra top-level fields in {body}");
    message.to_owned()
}
