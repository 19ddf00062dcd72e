-- The whole schema for PostgreSQL, equal in meaning to migrations/sqlite/0001-0005 (see those
-- files for what each column holds). Types are the ones both backends read alike through one
-- store: TEXT, BIGINT, DOUBLE PRECISION, BYTEA. Times are RFC 3339 text (UTC, milliseconds,
-- sorting in time order) as in SQLite; flags are BIGINT 0/1; lease times are milliseconds since
-- the Unix epoch from the database's clock.

CREATE TABLE datasets (
    id               TEXT PRIMARY KEY NOT NULL,
    name             TEXT NOT NULL,
    description      TEXT,
    format           TEXT NOT NULL,
    transitions      BIGINT NOT NULL,
    episodes         BIGINT NOT NULL,
    obs_dim          BIGINT NOT NULL,
    action_space     TEXT NOT NULL,
    stats            TEXT NOT NULL,
    sha256           TEXT NOT NULL,
    bytes            BIGINT NOT NULL,
    canonical_sha256 TEXT NOT NULL,
    canonical_bytes  BIGINT NOT NULL,
    created_at       TEXT NOT NULL
);
CREATE INDEX datasets_by_created_at ON datasets (created_at);

-- A dataset's canonical bytes, in chunks (no shared file system between machines; a chunk well
-- below PostgreSQL's 1 GB field limit, so uploads up to --max-upload-bytes fit).
CREATE TABLE dataset_chunks (
    dataset_id TEXT NOT NULL REFERENCES datasets (id) ON DELETE CASCADE,
    seq        BIGINT NOT NULL,
    data       BYTEA NOT NULL,
    PRIMARY KEY (dataset_id, seq)
);

CREATE TABLE jobs (
    id                       TEXT PRIMARY KEY NOT NULL,
    algorithm                TEXT NOT NULL,
    status                   TEXT NOT NULL
        CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    unlabeled_dataset_id     TEXT NOT NULL,
    non_preferred_dataset_id TEXT,
    created_at               TEXT NOT NULL,
    updated_at               TEXT NOT NULL,
    config                   TEXT NOT NULL DEFAULT '{}',
    runner                   TEXT NOT NULL DEFAULT '{}',
    step                     BIGINT NOT NULL DEFAULT 0,
    total_steps              BIGINT NOT NULL DEFAULT 0,
    phase                    TEXT,
    iterations_per_second    DOUBLE PRECISION,
    alpha_hat                DOUBLE PRECISION,
    policy_id                TEXT,
    error                    TEXT,
    cancel_requested         BIGINT NOT NULL DEFAULT 0,
    started_at               TEXT,
    finished_at              TEXT,
    eval                     TEXT,
    lease_owner              TEXT,
    lease_token              BIGINT NOT NULL DEFAULT 0,
    lease_expires_ms         BIGINT NOT NULL DEFAULT 0,
    lease_takeovers          BIGINT NOT NULL DEFAULT 0
);
CREATE INDEX jobs_by_status ON jobs (status);
CREATE INDEX jobs_by_unlabeled_dataset ON jobs (unlabeled_dataset_id);
CREATE INDEX jobs_by_non_preferred_dataset ON jobs (non_preferred_dataset_id);
CREATE INDEX jobs_by_created_at ON jobs (created_at);

CREATE TABLE job_metrics (
    job_id TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    name   TEXT NOT NULL,
    step   BIGINT NOT NULL,
    value  DOUBLE PRECISION NOT NULL,
    time   TEXT NOT NULL,
    PRIMARY KEY (job_id, name, step)
);

CREATE TABLE job_checkpoints (
    job_id     TEXT PRIMARY KEY NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    step       BIGINT NOT NULL,
    data       BYTEA NOT NULL,
    created_at TEXT NOT NULL
);

CREATE TABLE policies (
    id            TEXT PRIMARY KEY NOT NULL,
    job_id        TEXT NOT NULL REFERENCES jobs (id),
    algorithm     TEXT NOT NULL,
    obs_dim       BIGINT NOT NULL,
    action_space  TEXT NOT NULL,
    spec          TEXT NOT NULL,
    weights       BYTEA NOT NULL,
    final_metrics TEXT NOT NULL,
    alpha_hat     DOUBLE PRECISION,
    created_at    TEXT NOT NULL
);
CREATE INDEX policies_by_job ON policies (job_id);

CREATE TABLE evaluations (
    id               TEXT PRIMARY KEY NOT NULL,
    policy_id        TEXT NOT NULL REFERENCES policies (id) ON DELETE CASCADE,
    env              TEXT NOT NULL,
    episodes         BIGINT NOT NULL,
    seed             BIGINT NOT NULL,
    deterministic    BIGINT NOT NULL,
    status           TEXT NOT NULL
        CHECK (status IN ('queued', 'running', 'succeeded', 'failed')),
    report           TEXT,
    error            TEXT,
    created_at       TEXT NOT NULL,
    started_at       TEXT,
    finished_at      TEXT,
    lease_owner      TEXT,
    lease_token      BIGINT NOT NULL DEFAULT 0,
    lease_expires_ms BIGINT NOT NULL DEFAULT 0
);
CREATE INDEX evaluations_by_policy ON evaluations (policy_id, created_at);
CREATE INDEX evaluations_by_status ON evaluations (status, created_at);

CREATE TABLE workers (
    id           TEXT PRIMARY KEY NOT NULL,
    host         TEXT NOT NULL,
    pid          BIGINT NOT NULL,
    concurrency  BIGINT NOT NULL,
    started_at   TEXT NOT NULL,
    heartbeat_ms BIGINT NOT NULL
);
