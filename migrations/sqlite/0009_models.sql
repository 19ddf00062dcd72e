-- Named models for deployment: numbered versions, each pointing at a policy, and aliases
-- (`production`, `staging`, …) pointing at a version, every move of an alias kept.

CREATE TABLE models (
    name         TEXT PRIMARY KEY NOT NULL,
    description  TEXT NOT NULL DEFAULT '',
    tags         TEXT NOT NULL DEFAULT '[]',  -- JSON list of tags
    last_version INTEGER NOT NULL DEFAULT 0,  -- the highest number handed out: never reused
    revision     INTEGER NOT NULL DEFAULT 0,  -- bumped by every change serving must see
    created_at   TEXT NOT NULL,               -- RFC 3339, UTC
    updated_at   TEXT NOT NULL
);

CREATE TABLE model_versions (
    model       TEXT NOT NULL REFERENCES models (name) ON DELETE CASCADE,
    version     INTEGER NOT NULL,
    policy_id   TEXT NOT NULL REFERENCES policies (id),
    description TEXT NOT NULL DEFAULT '',
    source      TEXT NOT NULL,                -- who registered it: `api`, or `job <id>`
    created_at  TEXT NOT NULL,
    PRIMARY KEY (model, version)
);
CREATE INDEX model_versions_by_policy ON model_versions (policy_id);

-- An alias answers from `version`, or from `canary_version` for `canary_basis_points` of every
-- 10,000 requests.
CREATE TABLE model_aliases (
    model               TEXT NOT NULL REFERENCES models (name) ON DELETE CASCADE,
    alias               TEXT NOT NULL,
    version             INTEGER NOT NULL,
    canary_version      INTEGER,
    canary_basis_points INTEGER,
    updated_at          TEXT NOT NULL,
    PRIMARY KEY (model, alias),
    FOREIGN KEY (model, version) REFERENCES model_versions (model, version),
    FOREIGN KEY (model, canary_version) REFERENCES model_versions (model, version)
);

-- Every move of an alias: `seq` is the model's revision the move made; `to_version` NULL is a
-- delete.
CREATE TABLE model_alias_moves (
    model                  TEXT NOT NULL REFERENCES models (name) ON DELETE CASCADE,
    seq                    INTEGER NOT NULL,
    alias                  TEXT NOT NULL,
    from_version           INTEGER,
    from_canary_version    INTEGER,
    from_canary_basis_points INTEGER,
    to_version             INTEGER,
    to_canary_version      INTEGER,
    to_canary_basis_points INTEGER,
    actor                  TEXT NOT NULL,
    reason                 TEXT,
    moved_at               TEXT NOT NULL,
    PRIMARY KEY (model, seq)
);

-- A job that registers its policy as the next version of a model when it succeeds, and the
-- alias (if any) it then moves to that version.
ALTER TABLE jobs ADD COLUMN register_model TEXT;
ALTER TABLE jobs ADD COLUMN register_alias TEXT;
