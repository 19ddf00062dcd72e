-- Policy evaluations on the built-in environments (POST /v1/policies/{id}/evaluate), run in the
-- background one at a time; and each job's optional `eval` block.

-- The job's eval block (JSON, jobs::EvalOptions), NULL when the job does not evaluate.
ALTER TABLE jobs ADD COLUMN eval TEXT;

CREATE TABLE evaluations (
    id            TEXT PRIMARY KEY NOT NULL,
    policy_id     TEXT NOT NULL REFERENCES policies (id) ON DELETE CASCADE,
    env           TEXT NOT NULL,
    episodes      INTEGER NOT NULL,
    seed          INTEGER NOT NULL,
    deterministic INTEGER NOT NULL,
    status        TEXT NOT NULL
        CHECK (status IN ('queued', 'running', 'succeeded', 'failed')),
    report        TEXT,              -- JSON, envs::EvalReport, once succeeded
    error         TEXT,              -- why it failed
    created_at    TEXT NOT NULL,     -- RFC 3339, UTC
    started_at    TEXT,
    finished_at   TEXT
);

CREATE INDEX evaluations_by_policy ON evaluations (policy_id, created_at);
CREATE INDEX evaluations_by_status ON evaluations (status, created_at);
