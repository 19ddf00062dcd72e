-- An alias's shadow: `shadow_version` runs beside the alias's answer on `shadow_basis_points` of
-- every 10,000 requests and is compared with it, never returned. No foreign key, as on SQLite
-- (which cannot add one to an existing table): the store refuses to delete a version in use as a
-- shadow, as one in use as a version or canary.
ALTER TABLE model_aliases ADD COLUMN shadow_version BIGINT;
ALTER TABLE model_aliases ADD COLUMN shadow_basis_points BIGINT;
ALTER TABLE model_alias_moves ADD COLUMN from_shadow_version BIGINT;
ALTER TABLE model_alias_moves ADD COLUMN from_shadow_basis_points BIGINT;
ALTER TABLE model_alias_moves ADD COLUMN to_shadow_version BIGINT;
ALTER TABLE model_alias_moves ADD COLUMN to_shadow_basis_points BIGINT;

-- The comparison of a shadow with the version that answered, per minute (`minute`: RFC 3339 of
-- the minute's start, UTC). Every serving process adds its counts to the same row, so a fleet's
-- nodes make one series. Sums and maxima, so the means are sum / count.
CREATE TABLE shadow_comparisons (
    model                   TEXT NOT NULL,
    alias                   TEXT NOT NULL,
    production_version      BIGINT NOT NULL,
    shadow_version          BIGINT NOT NULL,
    minute                  TEXT NOT NULL,
    -- Requests drawn for the shadow: compared, skipped (the shadow's queue was full) or failed.
    requests                BIGINT NOT NULL,
    skipped                 BIGINT NOT NULL,
    failures                BIGINT NOT NULL,
    -- Observations compared, and the shadow's compute time in nanoseconds.
    observations            BIGINT NOT NULL,
    shadow_ns               BIGINT NOT NULL,
    -- Discrete actions: observations where the two versions chose differently.
    disagreements           BIGINT NOT NULL,
    -- Continuous actions: the L2 and largest absolute difference per observation.
    l2_sum                  DOUBLE PRECISION NOT NULL,
    l2_max                  DOUBLE PRECISION NOT NULL,
    max_abs_sum             DOUBLE PRECISION NOT NULL,
    max_abs_max             DOUBLE PRECISION NOT NULL,
    -- Safety scores (docs/safety-scores.md), where the version has the head: sums and counts.
    shadow_log_ratio_sum    DOUBLE PRECISION NOT NULL,
    shadow_log_ratio_n      BIGINT NOT NULL,
    production_log_ratio_sum DOUBLE PRECISION NOT NULL,
    production_log_ratio_n  BIGINT NOT NULL,
    out_of_support_sum      DOUBLE PRECISION NOT NULL,
    out_of_support_n        BIGINT NOT NULL,
    PRIMARY KEY (model, alias, production_version, shadow_version, minute)
);
