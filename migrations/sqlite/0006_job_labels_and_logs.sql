-- What people call a job (name, tags, notes: never read by the runner) and each job's log.

ALTER TABLE jobs ADD COLUMN name TEXT;
-- JSON array of tags; a tag holds no `"`, so `tags LIKE '%"<tag>"%'` finds it exactly.
ALTER TABLE jobs ADD COLUMN tags TEXT NOT NULL DEFAULT '[]';
ALTER TABLE jobs ADD COLUMN notes TEXT;

-- The lines a worker wrote about a job (started, resumed, phases, alpha-hat, evaluations,
-- checkpoints, how it ended), numbered per job in the order they were stored.
CREATE TABLE job_logs (
    job_id  TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    seq     INTEGER NOT NULL,
    time    TEXT NOT NULL,           -- RFC 3339, UTC
    level   TEXT NOT NULL CHECK (level IN ('info', 'warn', 'error')),
    worker  TEXT NOT NULL,
    message TEXT NOT NULL,
    PRIMARY KEY (job_id, seq)
) WITHOUT ROWID;
