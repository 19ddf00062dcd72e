-- An alias's shadow: `shadow_version` runs beside the alias's answer on `shadow_basis_points` of
-- every 10,000 requests and is compared with it, never returned. (SQLite cannot add a composite
-- foreign key to an existing table; a version in use as a shadow is refused deletion by the
-- store, as one in use as a version or canary is.)
ALTER TABLE model_aliases ADD COLUMN shadow_version INTEGER;
ALTER TABLE model_aliases ADD COLUMN shadow_basis_points INTEGER;
ALTER TABLE model_alias_moves ADD COLUMN from_shadow_version INTEGER;
ALTER TABLE model_alias_moves ADD COLUMN from_shadow_basis_points INTEGER;
ALTER TABLE model_alias_moves ADD COLUMN to_shadow_version INTEGER;
ALTER TABLE model_alias_moves ADD COLUMN to_shadow_basis_points INTEGER;

-- The comparison of a shadow with the version that answered, per minute (`minute`: RFC 3339 of
-- the minute's start, UTC). Every serving process adds its counts to the same row, so a fleet's
-- nodes make one series. Sums and maxima, so the means are sum / count.
CREATE TABLE shadow_comparisons (
    model                   TEXT NOT NULL,
    alias                   TEXT NOT NULL,
    production_version      INTEGER NOT NULL,
    shadow_version          INTEGER NOT NULL,
    minute                  TEXT NOT NULL,
    -- Requests drawn for the shadow: compared, skipped (the shadow's queue was full) or failed.
    requests                INTEGER NOT NULL,
    skipped                 INTEGER NOT NULL,
    failures                INTEGER NOT NULL,
    -- Observations compared, and the shadow's compute time in nanoseconds.
    observations            INTEGER NOT NULL,
    shadow_ns               INTEGER NOT NULL,
    -- Discrete actions: observations where the two versions chose differently.
    disagreements           INTEGER NOT NULL,
    -- Continuous actions: the L2 and largest absolute difference per observation.
    l2_sum                  REAL NOT NULL,
    l2_max                  REAL NOT NULL,
    max_abs_sum             REAL NOT NULL,
    max_abs_max             REAL NOT NULL,
    -- Safety scores (docs/safety-scores.md), where the version has the head: sums and counts.
    shadow_log_ratio_sum    REAL NOT NULL,
    shadow_log_ratio_n      INTEGER NOT NULL,
    production_log_ratio_sum REAL NOT NULL,
    production_log_ratio_n  INTEGER NOT NULL,
    out_of_support_sum      REAL NOT NULL,
    out_of_support_n        INTEGER NOT NULL,
    PRIMARY KEY (model, alias, production_version, shadow_version, minute)
);
