-- A deployment's own impostor thresholds per model version (`facegate calibrate`,
-- facegate_vision::recognize::site): JSON of a SiteCalibration. Aggregates only (thresholds and
-- counts): no template or subject id, so erasing a subject leaves nothing of it here.
CREATE TABLE site_calibrations (
    model_version  TEXT PRIMARY KEY NOT NULL,
    calibration    TEXT NOT NULL,
    created_at     TEXT NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ', 'now'))
) STRICT;
