-- Experiments; the same as migrations/sqlite/0010_experiments.sql.
CREATE TABLE experiments (
    id         TEXT PRIMARY KEY NOT NULL,
    name       TEXT,
    spec       TEXT NOT NULL,   -- JSON: datasets, arms (label, algorithm, config), seeds, eval
    created_at TEXT NOT NULL    -- RFC 3339, UTC
);

ALTER TABLE jobs ADD COLUMN experiment_id TEXT REFERENCES experiments (id);
ALTER TABLE jobs ADD COLUMN experiment_arm TEXT;
CREATE INDEX jobs_by_experiment ON jobs (experiment_id);
