-- How the policy acted in an evaluation's episodes (domain::EvalRuntime): part of the evaluation
-- protocol that results are grouped by. 'builtin' for the service's own; 'act', 'onnx' or
-- 'other' as an external recording says; NULL on rows from before this column, read as
-- 'builtin' or 'unspecified' by their source.
ALTER TABLE evaluations ADD COLUMN runtime TEXT
    CHECK (runtime IN ('builtin', 'act', 'onnx', 'other', 'unspecified'));
