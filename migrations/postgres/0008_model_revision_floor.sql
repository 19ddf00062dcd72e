-- A model's revision never goes back under its name: the highest revision a deleted model
-- reached is kept here, and a model created afterwards starts above it. A serving process that
-- still holds the deleted model's table then sees the new model as newer and loads it; without
-- this a re-created model started at revision 0 and every other node kept its old routes.
CREATE TABLE model_revision_floor (
    id       INTEGER PRIMARY KEY NOT NULL CHECK (id = 1),
    revision BIGINT NOT NULL
);
INSERT INTO model_revision_floor (id, revision) SELECT 1, COALESCE(MAX(revision), 0) FROM models;
