-- Schema version 2: idempotency records (decision D5). A request sent with an
-- `Idempotency-Key` stores what it did in the same transaction as the change itself, so a retry
-- on any replica — also after a crash of the first — finds both or neither. The primary key
-- makes two concurrent requests with one key apply once. Each record belongs to a map (for a
-- trip's batches, the trip's map), so deleting the map deletes its records.
CREATE TABLE idempotency_keys (
    scope       TEXT   NOT NULL,
    key         TEXT   NOT NULL,
    map_id      BIGINT NOT NULL REFERENCES maps (id) ON DELETE CASCADE,
    fingerprint BYTEA  NOT NULL,
    response    BYTEA  NOT NULL,
    first       BIGINT,
    count       BIGINT,
    created_ms  BIGINT NOT NULL,
    PRIMARY KEY (scope, key)
);
CREATE INDEX idempotency_keys_by_map ON idempotency_keys (map_id);
