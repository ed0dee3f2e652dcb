-- Templates at rest (src/store/cipher.rs): each subject may hold a data key wrapped by a master
-- key (`data_key`, with the master key's id in `key_id`); then all of its template vectors are
-- sealed under that data key (nonce, ciphertext, tag: 28 bytes more than the plain vector).
-- A subject without a data key keeps plain vectors (no key configured, or not yet `facegate rekey`ed).
ALTER TABLE subjects ADD COLUMN key_id TEXT;
ALTER TABLE subjects ADD COLUMN data_key BLOB;

-- SQLite cannot change a CHECK constraint in place: the templates table is rebuilt with the
-- sealed length allowed. Nothing references it, so dropping the old table is safe.
CREATE TABLE templates_sealed (
    id             INTEGER PRIMARY KEY,
    subject_id     TEXT NOT NULL REFERENCES subjects (id) ON DELETE CASCADE,
    model_version  TEXT NOT NULL,
    dimension      INTEGER NOT NULL CHECK (dimension > 0),
    vector         BLOB NOT NULL CHECK (length(vector) IN (4 * dimension, 4 * dimension + 28)),
    created_at     TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
) STRICT;
INSERT INTO templates_sealed (id, subject_id, model_version, dimension, vector, created_at)
    SELECT id, subject_id, model_version, dimension, vector, created_at FROM templates;
DROP TABLE templates;
ALTER TABLE templates_sealed RENAME TO templates;
CREATE INDEX templates_by_subject ON templates (subject_id, model_version);
CREATE INDEX templates_by_model ON templates (model_version, subject_id);
