-- seasonloc on PostgreSQL, schema version 1 (applied by src/store/postgres/migrate.rs at start-up,
-- in order, under an advisory lock, each file in its own transaction; see migrations/README.md).
--
-- Ids are allocated from one sequence (increasing with creation time, like the embedded
-- engine's). Every child row references its map or trip with ON DELETE CASCADE, so deleting a
-- map is one statement, atomic with everything under it.

CREATE SEQUENCE seasonloc_ids START 1;

-- `settings` is the descriptor settings, encoded as a layout-4 map record
-- (crate::store::sled::codec::encode_map; one encoding of the settings for both engines). Its
-- id, dim, image_count and created_ms fields are unused: the columns below are authoritative.
-- `image_count` is also the version of the map's descriptor matrix (images are append-only).
CREATE TABLE maps (
    id          BIGINT PRIMARY KEY,
    name        TEXT   NOT NULL,
    settings    BYTEA  NOT NULL,
    dim         BIGINT CHECK (dim >= 0),
    image_count BIGINT NOT NULL DEFAULT 0 CHECK (image_count >= 0),
    created_ms  BIGINT NOT NULL
);

-- Reference images, one row per appended batch: images first .. first + count of the map.
-- `descriptors` is count x dim little-endian f32, row-major (dim 0 and empty for co-occurrence
-- maps, whose images have no descriptor rows); `metas` one encoded metadata record per image
-- (crate::store::sled::codec::encode_image with an empty descriptor).
CREATE TABLE image_batches (
    map_id      BIGINT  NOT NULL REFERENCES maps (id) ON DELETE CASCADE,
    first       BIGINT  NOT NULL CHECK (first >= 0),
    count       BIGINT  NOT NULL CHECK (count > 0),
    dim         BIGINT  NOT NULL CHECK (dim >= 0),
    descriptors BYTEA   NOT NULL,
    metas       BYTEA[] NOT NULL,
    PRIMARY KEY (map_id, first)
);
-- Float data does not compress: store it out of line without trying.
ALTER TABLE image_batches ALTER COLUMN descriptors SET STORAGE EXTERNAL;

-- The encoded CoocMap of a co-occurrence map (opaque to the store).
CREATE TABLE cooc_maps (
    map_id  BIGINT PRIMARY KEY REFERENCES maps (id) ON DELETE CASCADE,
    encoded BYTEA  NOT NULL
);

-- Localization results; `document` is the stored JSON (crate::store::document).
CREATE TABLE localizations (
    id         BIGINT PRIMARY KEY,
    map_id     BIGINT NOT NULL REFERENCES maps (id) ON DELETE CASCADE,
    created_ms BIGINT NOT NULL,
    document   BYTEA  NOT NULL
);
CREATE INDEX localizations_by_map ON localizations (map_id, id);

-- Trips: the record, its parameters (JSON, crate::store::document) and the solver state
-- (opaque bytes owned by crate::trip). `frame_count` is the state's version: a batch updates
-- the row only where it still has the count the batch was computed after.
-- `status`: 0 before the first batch, 1 localized, 2 lost, 3 relocalized.
CREATE TABLE trips (
    id              BIGINT   PRIMARY KEY,
    map_id          BIGINT   NOT NULL REFERENCES maps (id) ON DELETE CASCADE,
    created_ms      BIGINT   NOT NULL,
    closed_ms       BIGINT,
    frame_count     BIGINT   NOT NULL CHECK (frame_count >= 0),
    reference_count BIGINT   NOT NULL CHECK (reference_count >= 0),
    status          SMALLINT NOT NULL,
    params          BYTEA    NOT NULL,
    state           BYTEA    NOT NULL
);
ALTER TABLE trips ALTER COLUMN state SET STORAGE EXTERNAL;
CREATE INDEX trips_by_map ON trips (map_id, id);

-- Each frame's latest estimate (rewritten when the lag window revises it).
CREATE TABLE trip_frames (
    trip_id    BIGINT NOT NULL REFERENCES trips (id) ON DELETE CASCADE,
    frame      BIGINT NOT NULL CHECK (frame >= 0),
    reference  BIGINT,
    confidence DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (trip_id, frame)
);
