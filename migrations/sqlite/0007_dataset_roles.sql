-- What a dataset is for, as the uploader said: `unlabeled` (D^U) or `non_preferred` (D^N);
-- NULL when not said. Jobs check it: a dataset uploaded as one is refused in the other's place.
ALTER TABLE datasets ADD COLUMN role TEXT CHECK (role IN ('unlabeled', 'non_preferred'));
