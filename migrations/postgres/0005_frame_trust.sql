-- Schema version 5: a trip frame's calibrated p_correct and status (the sled layout's step
-- 0007). Rows written by schema 1-4 have both NULL and are read with p_correct 0 and the status
-- off_map (no reference) or uncertain (a reference nothing calibrated); a later batch that
-- revises a frame writes both. status: 1 localized, 2 uncertain, 3 off_map, 4 lost.
ALTER TABLE trip_frames ADD COLUMN p_correct DOUBLE PRECISION;
ALTER TABLE trip_frames ADD COLUMN status SMALLINT;
ALTER TABLE trip_frames ADD CONSTRAINT trip_frames_trust
    CHECK ((p_correct IS NULL) = (status IS NULL) AND (status IS NULL OR status BETWEEN 1 AND 4));
