-- Dataset roles; the same as migrations/sqlite/0007_dataset_roles.sql.
ALTER TABLE datasets ADD COLUMN role TEXT CHECK (role IN ('unlabeled', 'non_preferred'));
