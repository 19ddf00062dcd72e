-- Training evaluations; the same as migrations/sqlite/0011_training_evaluations.sql.
ALTER TABLE evaluations ADD COLUMN training_step BIGINT;
