-- Schema version 4: a trip's state in parts, written as a delta per batch (the sled layout's
-- step 0006; formats in src/trip/persist.rs).
--
-- Schema 1-3 kept the whole solver state in `trips.state` and every batch rewrote it: about
-- 1 MB of WAL per batch at lag 32 on a 2,400-image map, 13 MB on 30,790 images. Now:
-- `trips.base`     the parameters and the map's prior (4 x D bytes), written once at open;
-- `trips.snapshot` the trip at the start of its lag window (about 32 x D bytes), rewritten by
--                  the first batch and then once the log holds 2 x lag rows; a batch that
--                  does not change it leaves the stored value (and its TOAST chunks) alone;
-- `trip_log`       one row per frame since the snapshot: the frame's raw cosine row (4 x D
--                  bytes), inserted by its batch; the rows before a new snapshot are deleted
--                  in the same transaction.
-- `trips.state` stays for trips written by schema 1-3 (a format-1 blob, still read); their
-- next batch writes `base` and `snapshot` and sets `state` to NULL in the same transaction.
-- New trips have `state` NULL and `base` set.
ALTER TABLE trips ALTER COLUMN state DROP NOT NULL;
ALTER TABLE trips ADD COLUMN base BYTEA;
ALTER TABLE trips ADD COLUMN snapshot BYTEA;
ALTER TABLE trips ADD CONSTRAINT trips_state_or_parts
    CHECK ((state IS NULL) <> (base IS NULL) AND (base IS NULL) = (snapshot IS NULL));
-- Floats do not compress: keep them out of line, uncompressed.
ALTER TABLE trips ALTER COLUMN base SET STORAGE EXTERNAL;
ALTER TABLE trips ALTER COLUMN snapshot SET STORAGE EXTERNAL;

CREATE TABLE trip_log (
    trip_id BIGINT NOT NULL REFERENCES trips (id) ON DELETE CASCADE,
    frame   BIGINT NOT NULL CHECK (frame >= 0),
    row     BYTEA  NOT NULL,
    PRIMARY KEY (trip_id, frame)
);
ALTER TABLE trip_log ALTER COLUMN row SET STORAGE EXTERNAL;
