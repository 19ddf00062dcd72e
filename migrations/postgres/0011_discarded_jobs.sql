-- A job whose workers vanished `max_attempts` times ends `discarded`, apart from `failed` (the
-- training reported an error). Stored jobs that ended out of attempts (the reaper's message says
-- so) become `discarded`.
ALTER TABLE jobs DROP CONSTRAINT jobs_status_check;
ALTER TABLE jobs ADD CONSTRAINT jobs_status_check
    CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'cancelled', 'discarded'));
UPDATE jobs SET status = 'discarded' WHERE status = 'failed' AND error LIKE 'gave up after %';
