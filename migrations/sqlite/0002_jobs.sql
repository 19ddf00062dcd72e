-- The training queue. Only the columns the dataset API (no deleting a dataset a queued or running
-- job uses) and /metrics (jobs by status) read; the job runner adds the rest in later migrations.
CREATE TABLE jobs (
    id                       TEXT PRIMARY KEY NOT NULL,
    algorithm                TEXT NOT NULL,
    status                   TEXT NOT NULL
        CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    unlabeled_dataset_id     TEXT NOT NULL,
    non_preferred_dataset_id TEXT,
    created_at               TEXT NOT NULL,
    updated_at               TEXT NOT NULL
);

CREATE INDEX jobs_by_status ON jobs (status);
CREATE INDEX jobs_by_unlabeled_dataset ON jobs (unlabeled_dataset_id);
CREATE INDEX jobs_by_non_preferred_dataset ON jobs (non_preferred_dataset_id);
