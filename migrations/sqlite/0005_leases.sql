-- Leases: a running job (or evaluation) belongs to the worker that holds its lease until the
-- lease expires. Every write of a worker for the job names the lease token it claimed with, and
-- is refused once another worker has taken the job over (a new token). Times in milliseconds
-- since the Unix epoch, from the database's clock.
ALTER TABLE jobs ADD COLUMN lease_owner TEXT;
ALTER TABLE jobs ADD COLUMN lease_token INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN lease_expires_ms INTEGER NOT NULL DEFAULT 0;
-- Claims of this job after its previous worker's lease expired.
ALTER TABLE jobs ADD COLUMN lease_takeovers INTEGER NOT NULL DEFAULT 0;

ALTER TABLE evaluations ADD COLUMN lease_owner TEXT;
ALTER TABLE evaluations ADD COLUMN lease_token INTEGER NOT NULL DEFAULT 0;
ALTER TABLE evaluations ADD COLUMN lease_expires_ms INTEGER NOT NULL DEFAULT 0;

-- Worker processes (or the worker pool of a `serve` process) and their last heartbeat, for
-- /metrics; a row is removed when its worker stops cleanly.
CREATE TABLE workers (
    id                TEXT PRIMARY KEY NOT NULL,
    host              TEXT NOT NULL,
    pid               INTEGER NOT NULL,
    concurrency       INTEGER NOT NULL,
    started_at        TEXT NOT NULL,
    heartbeat_ms      INTEGER NOT NULL
);
