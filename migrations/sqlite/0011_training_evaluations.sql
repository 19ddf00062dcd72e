-- The evaluation a job's worker ran at the end of training (the job's `eval` block) is stored as
-- an evaluation of the job's policy, like one queued with `POST /v1/policies/{id}/evaluate`, so
-- every evaluation of a policy is in one table. `training_step` says which: the job's step it
-- ran at (its last); NULL for evaluations run after training.
ALTER TABLE evaluations ADD COLUMN training_step INTEGER;
