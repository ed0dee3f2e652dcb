//! The deployment's site calibration per model version (`facegate calibrate`,
//! [`facegate_vision::recognize::site`]): the enrolled subjects' impostor pairs, scored and
//! reduced to thresholds, stored as JSON beside the templates so that every replica reads the same.

use facegate_vision::recognize::SiteCalibration;
use facegate_vision::recognize::site::impostor_scores;

use crate::{Store, StoreError};

impl Store {
    /// The model versions the stored templates were made by.
    pub async fn model_versions(&self) -> Result<Vec<String>, StoreError> {
        Ok(sqlx::query_scalar("SELECT DISTINCT model_version FROM templates ORDER BY model_version").fetch_all(&self.pool).await?)
    }

    /// The site calibration of `model_version` from the enrolled subjects' templates: every pair
    /// of templates of two different subjects (sampled evenly beyond
    /// [`facegate_vision::recognize::site::MAX_TEMPLATES`]). A subject whose templates cannot be
    /// read is an error: a calibration must not silently leave subjects out.
    pub async fn measure_site_calibration(&self, model_version: &str) -> Result<SiteCalibration, StoreError> {
        #[derive(Default)]
        struct Rows {
            values: Vec<f32>,
            owners: Vec<u32>,
            dimension: usize,
            subjects: u32,
            error: Option<StoreError>,
        }
        let rows = self
            .gallery(model_version, Rows::default(), |rows, _subject, templates| match templates {
                Ok(templates) => {
                    for t in &templates {
                        // One model version has one dimension; a row of another is no pair to score.
                        if rows.dimension != 0 && t.vector.len() != rows.dimension {
                            continue;
                        }
                        rows.dimension = t.vector.len();
                        rows.values.extend_from_slice(&t.vector);
                        rows.owners.push(rows.subjects);
                    }
                    rows.subjects += 1;
                }
                Err(e) => {
                    rows.error.get_or_insert(e);
                }
            })
            .await?;
        if let Some(e) = rows.error {
            return Err(e);
        }
        let scores = impostor_scores(&rows.values, rows.dimension, &rows.owners);
        Ok(SiteCalibration::from_impostor_scores(model_version, rows.subjects as usize, rows.owners.len(), &scores))
    }

    /// The stored site calibration of `model_version`, if any.
    pub async fn site_calibration(&self, model_version: &str) -> Result<Option<SiteCalibration>, StoreError> {
        let json: Option<String> = sqlx::query_scalar("SELECT calibration FROM site_calibrations WHERE model_version = $1")
            .bind(model_version)
            .fetch_optional(&self.pool)
            .await?;
        json.map(|j| {
            serde_json::from_str(&j).map_err(|e| StoreError::Refused(format!("the site calibration of {model_version} is unreadable: {e}")))
        })
        .transpose()
    }

    /// Store `calibration` for its model version, replacing the one before.
    pub async fn set_site_calibration(&self, calibration: &SiteCalibration) -> Result<(), StoreError> {
        let json = serde_json::to_string(calibration).map_err(|e| StoreError::Refused(e.to_string()))?;
        sqlx::query(
            "INSERT INTO site_calibrations (model_version, calibration) VALUES ($1, $2) \
             ON CONFLICT (model_version) DO UPDATE SET calibration = excluded.calibration, created_at = excluded.created_at",
        )
        .bind(&calibration.model_version)
        .bind(json)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Remove the site calibration of `model_version`; whether there was one.
    pub async fn clear_site_calibration(&self, model_version: &str) -> Result<bool, StoreError> {
        let done = sqlx::query("DELETE FROM site_calibrations WHERE model_version = $1").bind(model_version).execute(&self.pool).await?;
        Ok(done.rows_affected() > 0)
    }
}
