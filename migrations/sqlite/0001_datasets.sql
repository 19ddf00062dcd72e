-- Uploaded datasets. The data itself is stored once, in the canonical binary form, as the file
-- datasets/<id>.canonical in the data directory; this row describes it.
CREATE TABLE datasets (
    id               TEXT PRIMARY KEY NOT NULL,
    name             TEXT NOT NULL,
    description      TEXT,
    format           TEXT NOT NULL,             -- upload format: jsonl | csv | npz | hdf5
    transitions      INTEGER NOT NULL,
    episodes         INTEGER NOT NULL,
    obs_dim          INTEGER NOT NULL,
    action_space     TEXT NOT NULL,             -- JSON, the API's ActionSpace
    stats            TEXT NOT NULL,             -- JSON, the API's DatasetStats
    sha256           TEXT NOT NULL,             -- of the uploaded file, hex
    bytes            INTEGER NOT NULL,          -- of the uploaded file
    canonical_sha256 TEXT NOT NULL,             -- of the stored canonical file, checked on load
    canonical_bytes  INTEGER NOT NULL,
    created_at       TEXT NOT NULL              -- RFC 3339, UTC
);
