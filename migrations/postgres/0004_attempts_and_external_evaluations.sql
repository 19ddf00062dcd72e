-- Attempts, each claim's outcome, the workers' memory, external evaluations; the same as
-- migrations/sqlite/0008_attempts_and_external_evaluations.sql.
ALTER TABLE jobs ADD COLUMN attempt BIGINT NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN max_attempts BIGINT NOT NULL DEFAULT 3;
ALTER TABLE jobs ADD COLUMN scheduled_ms BIGINT NOT NULL DEFAULT 0;

CREATE TABLE job_attempts (
    job_id     TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    claim      BIGINT NOT NULL,
    attempt    BIGINT NOT NULL,
    worker     TEXT NOT NULL,
    started_at TEXT NOT NULL,
    ended_at   TEXT,
    outcome    TEXT NOT NULL CHECK (outcome IN ('running', 'succeeded', 'failed', 'cancelled',
                                                'released', 'crashed', 'lease_lost')),
    message    TEXT,
    PRIMARY KEY (job_id, claim)
);

ALTER TABLE workers ADD COLUMN rss_bytes BIGINT;
ALTER TABLE workers ADD COLUMN memory_available_bytes BIGINT;

ALTER TABLE evaluations ADD COLUMN source TEXT NOT NULL DEFAULT 'builtin'
    CHECK (source IN ('builtin', 'external'));
