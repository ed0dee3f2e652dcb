-- Subjects and their face templates. No photo is ever stored: a template is a DLDA vector
-- (little-endian f32 BLOB) tagged with the recognition model version that produced it, since
-- vectors of different model versions live in different spaces and are not comparable.
CREATE TABLE subjects (
    id          TEXT PRIMARY KEY NOT NULL,
    created_at  TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now')),
    updated_at  TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
) STRICT;

CREATE TABLE templates (
    id             INTEGER PRIMARY KEY,
    subject_id     TEXT NOT NULL REFERENCES subjects (id) ON DELETE CASCADE,
    model_version  TEXT NOT NULL,
    dimension      INTEGER NOT NULL CHECK (dimension > 0),
    vector         BLOB NOT NULL CHECK (length(vector) = 4 * dimension),
    created_at     TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
) STRICT;

CREATE INDEX templates_by_subject ON templates (subject_id, model_version);
