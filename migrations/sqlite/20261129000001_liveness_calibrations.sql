-- A camera's liveness threshold per liveness model (`facegate calibrate-liveness`,
-- facegate_service::liveness_site): JSON of a LivenessCalibration. Aggregates only (a threshold
-- and counts): no photo, face or subject, so erasing a subject leaves nothing of it here.
CREATE TABLE liveness_calibrations (
    model        TEXT PRIMARY KEY NOT NULL,
    calibration  TEXT NOT NULL,
    created_at   TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
) STRICT;
