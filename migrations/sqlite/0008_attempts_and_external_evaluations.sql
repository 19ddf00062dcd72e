-- Attempts: how many times workers started a job, how many it may have, and when a job whose
-- worker died may be tried again (milliseconds since the Unix epoch on the database's clock,
-- 0 for at once). A run handed back on shutdown does not count as an attempt.
ALTER TABLE jobs ADD COLUMN attempt INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN max_attempts INTEGER NOT NULL DEFAULT 3;
ALTER TABLE jobs ADD COLUMN scheduled_ms INTEGER NOT NULL DEFAULT 0;

-- Every claim of a job by a worker and how it ended (`outcome`): still running, succeeded,
-- failed, cancelled, released (shutdown or a store that could not take writes: given back),
-- crashed (the worker stopped renewing its lease) or lease_lost (the worker came back after
-- another had taken the job over). `claim` is the claim's lease token.
CREATE TABLE job_attempts (
    job_id     TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    claim      INTEGER NOT NULL,
    attempt    INTEGER NOT NULL,
    worker     TEXT NOT NULL,
    started_at TEXT NOT NULL,         -- RFC 3339, UTC
    ended_at   TEXT,
    outcome    TEXT NOT NULL CHECK (outcome IN ('running', 'succeeded', 'failed', 'cancelled',
                                                'released', 'crashed', 'lease_lost')),
    message    TEXT,
    PRIMARY KEY (job_id, claim)
) WITHOUT ROWID;

-- What a worker process last said of its memory (at its registry heartbeat), so the end of a
-- job whose worker vanished can say whether memory ran out.
ALTER TABLE workers ADD COLUMN rss_bytes INTEGER;
ALTER TABLE workers ADD COLUMN memory_available_bytes INTEGER;

-- Where an evaluation's episodes ran: `builtin` (queued, run by a worker on a built-in
-- environment) or `external` (the user's own simulator; recorded with its per-episode returns
-- and costs, the metrics computed by the service, already succeeded).
ALTER TABLE evaluations ADD COLUMN source TEXT NOT NULL DEFAULT 'builtin'
    CHECK (source IN ('builtin', 'external'));
