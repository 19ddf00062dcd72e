-- A job whose workers vanished `max_attempts` times ends `discarded`, apart from `failed` (the
-- training reported an error). SQLite cannot change a CHECK constraint in place, so the table is
-- rebuilt the way SQLite documents (ALTER TABLE, "other kinds of table schema changes"). The
-- store runs migrations with foreign keys off (Store::open), so dropping the old table cascades
-- to none of the rows that reference a job; they keep naming `jobs`, which the rebuilt table
-- becomes. The columns keep their order and every value.
CREATE TABLE jobs_rebuilt (
    id                       TEXT PRIMARY KEY NOT NULL,
    algorithm                TEXT NOT NULL,
    status                   TEXT NOT NULL
        CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled', 'discarded')),
    unlabeled_dataset_id     TEXT NOT NULL,
    non_preferred_dataset_id TEXT,
    created_at               TEXT NOT NULL,
    updated_at               TEXT NOT NULL,
    config                   TEXT NOT NULL DEFAULT '{}',
    runner                   TEXT NOT NULL DEFAULT '{}',
    step                     INTEGER NOT NULL DEFAULT 0,
    total_steps              INTEGER NOT NULL DEFAULT 0,
    phase                    TEXT,
    iterations_per_second    REAL,
    alpha_hat                REAL,
    policy_id                TEXT,
    error                    TEXT,
    cancel_requested         INTEGER NOT NULL DEFAULT 0,
    started_at               TEXT,
    finished_at              TEXT,
    eval                     TEXT,
    lease_owner              TEXT,
    lease_token              INTEGER NOT NULL DEFAULT 0,
    lease_expires_ms         INTEGER NOT NULL DEFAULT 0,
    lease_takeovers          INTEGER NOT NULL DEFAULT 0,
    name                     TEXT,
    tags                     TEXT NOT NULL DEFAULT '[]',
    notes                    TEXT,
    attempt                  INTEGER NOT NULL DEFAULT 0,
    max_attempts             INTEGER NOT NULL DEFAULT 3,
    scheduled_ms             INTEGER NOT NULL DEFAULT 0,
    register_model           TEXT,
    register_alias           TEXT,
    experiment_id            TEXT REFERENCES experiments (id),
    experiment_arm           TEXT
);
INSERT INTO jobs_rebuilt (
    id, algorithm, status, unlabeled_dataset_id, non_preferred_dataset_id, created_at, updated_at,
    config, runner, step, total_steps, phase, iterations_per_second, alpha_hat, policy_id, error,
    cancel_requested, started_at, finished_at, eval, lease_owner, lease_token, lease_expires_ms,
    lease_takeovers, name, tags, notes, attempt, max_attempts, scheduled_ms, register_model,
    register_alias, experiment_id, experiment_arm)
SELECT
    id, algorithm, status, unlabeled_dataset_id, non_preferred_dataset_id, created_at, updated_at,
    config, runner, step, total_steps, phase, iterations_per_second, alpha_hat, policy_id, error,
    cancel_requested, started_at, finished_at, eval, lease_owner, lease_token, lease_expires_ms,
    lease_takeovers, name, tags, notes, attempt, max_attempts, scheduled_ms, register_model,
    register_alias, experiment_id, experiment_arm
FROM jobs;
DROP TABLE jobs;
ALTER TABLE jobs_rebuilt RENAME TO jobs;
CREATE INDEX jobs_by_status ON jobs (status);
CREATE INDEX jobs_by_unlabeled_dataset ON jobs (unlabeled_dataset_id);
CREATE INDEX jobs_by_non_preferred_dataset ON jobs (non_preferred_dataset_id);
CREATE INDEX jobs_by_created_at ON jobs (created_at);
CREATE INDEX jobs_by_experiment ON jobs (experiment_id);
-- Stored jobs that ended out of attempts (the reaper's message says so) become `discarded`.
UPDATE jobs SET status = 'discarded' WHERE status = 'failed' AND error LIKE 'gave up after %';
