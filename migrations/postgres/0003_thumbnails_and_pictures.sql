-- Schema version 3: what the dashboard shows (issue 13; the sled layout's step 0005).
--
-- `image_batches.thumbnails`: one JPEG per image of the batch (at most 160 x 160 pixels,
-- src/picture/thumbnail.rs), written in the same INSERT as the batch's descriptors; NULL for a
-- batch without images (precomputed descriptors, batches stored before this version).
-- `localizations.picture`: the PNG of the result's similarity-matrix picture (at most 512 x 512
-- grey pixels, src/picture/matrix.rs), written in the same INSERT as the result; NULL when it
-- has none. Existing rows keep NULL: maps and results made before have no pictures (the same
-- rule as the embedded engine's migration 0005).
ALTER TABLE image_batches ADD COLUMN thumbnails BYTEA[];
ALTER TABLE localizations ADD COLUMN picture BYTEA;
-- JPEG and PNG are compressed already.
ALTER TABLE image_batches ALTER COLUMN thumbnails SET STORAGE EXTERNAL;
ALTER TABLE localizations ALTER COLUMN picture SET STORAGE EXTERNAL;
