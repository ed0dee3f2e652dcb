-- Open liveness challenges (POST /liveness/challenge): the steps drawn for each, until one
-- verification takes the row (single use) or it expires. Every replica reads the same table, so
-- a challenge issued by one is answered on any. No subject and no photo: only the drawn steps.
CREATE TABLE liveness_challenges (
    id          TEXT PRIMARY KEY NOT NULL,
    steps       TEXT NOT NULL,
    expires_at  BIGINT NOT NULL
);
CREATE INDEX liveness_challenges_expiry ON liveness_challenges (expires_at);
