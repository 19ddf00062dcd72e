-- What the job runner keeps: each job's resolved configuration and progress, its metrics history,
-- its latest checkpoint, and the trained policies.

-- The resolved algorithm configuration (JSON, as the API shows it and as a resume reads it back).
ALTER TABLE jobs ADD COLUMN config TEXT NOT NULL DEFAULT '{}';
-- The job-runner options (JSON: log_every, checkpoint_every, progress_every_ms).
ALTER TABLE jobs ADD COLUMN runner TEXT NOT NULL DEFAULT '{}';
-- Progress, updated while the job runs (at most a few times a second).
ALTER TABLE jobs ADD COLUMN step INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN total_steps INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN phase TEXT;
ALTER TABLE jobs ADD COLUMN iterations_per_second REAL;
ALTER TABLE jobs ADD COLUMN alpha_hat REAL;
-- Set once the job succeeded / failed.
ALTER TABLE jobs ADD COLUMN policy_id TEXT;
ALTER TABLE jobs ADD COLUMN error TEXT;
-- A cancel request for a running job: its worker stops at the next step.
ALTER TABLE jobs ADD COLUMN cancel_requested INTEGER NOT NULL DEFAULT 0;
-- First claimed by a worker (kept across resumes; interrupted jobs are claimed before new ones).
ALTER TABLE jobs ADD COLUMN started_at TEXT;
ALTER TABLE jobs ADD COLUMN finished_at TEXT;

CREATE INDEX jobs_by_created_at ON jobs (created_at);

-- One row per recorded (job, metric, step). The primary key makes a duplicate row impossible;
-- a resume deletes the rows past its checkpoint before recomputing them.
CREATE TABLE job_metrics (
    job_id TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    name   TEXT NOT NULL,
    step   INTEGER NOT NULL,
    value  REAL NOT NULL,
    time   TEXT NOT NULL,            -- RFC 3339, UTC
    PRIMARY KEY (job_id, name, step)
) WITHOUT ROWID;

-- The latest checkpoint of each job (Trainer::checkpoint bytes); replaced in place.
CREATE TABLE job_checkpoints (
    job_id     TEXT PRIMARY KEY NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    step       INTEGER NOT NULL,
    data       BLOB NOT NULL,
    created_at TEXT NOT NULL
);

-- Trained policies: the artefact (spec JSON + safetensors weights) and what the API lists.
CREATE TABLE policies (
    id            TEXT PRIMARY KEY NOT NULL,
    job_id        TEXT NOT NULL REFERENCES jobs (id),
    algorithm     TEXT NOT NULL,
    obs_dim       INTEGER NOT NULL,
    action_space  TEXT NOT NULL,     -- JSON, the API's ActionSpace
    spec          TEXT NOT NULL,     -- JSON, algo::PolicySpec
    weights       BLOB NOT NULL,     -- safetensors
    final_metrics TEXT NOT NULL,     -- JSON object: the last recorded value of each metric
    alpha_hat     REAL,
    created_at    TEXT NOT NULL
);

CREATE INDEX policies_by_job ON policies (job_id);
