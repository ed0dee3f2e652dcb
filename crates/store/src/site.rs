//! The deployment's site calibration per model version (`facegate calibrate`): kept as the JSON
//! text the service hands over, beside the templates, so that every replica reads the same. What
//! it holds and how it is measured is the service's (`facegate_service::site`); the store keeps
//! and returns rows. Also what one model version covers of the store.

use crate::{Store, StoreError};

impl Store {
    /// The model versions the stored templates were made by.
    pub async fn model_versions(&self) -> Result<Vec<String>, StoreError> {
        Ok(sqlx::query_scalar("SELECT DISTINCT model_version FROM templates ORDER BY model_version").fetch_all(&self.pool).await?)
    }

    /// Subjects with at least one template of `model_version`: those a search under that model
    /// can find (a subject enrolled only under another model is not among them).
    pub async fn subjects_of_version(&self, model_version: &str) -> Result<u64, StoreError> {
        let count: i64 = sqlx::query_scalar("SELECT count(DISTINCT subject_id) FROM templates WHERE model_version = $1")
            .bind(model_version)
            .fetch_one(&self.pool)
            .await?;
        Ok(count as u64)
    }

    /// The model versions with a stored site calibration.
    pub async fn calibrated_versions(&self) -> Result<Vec<String>, StoreError> {
        Ok(sqlx::query_scalar("SELECT model_version FROM site_calibrations ORDER BY model_version").fetch_all(&self.pool).await?)
    }

    /// The stored site calibration of `model_version` (its JSON text), if any.
    pub async fn site_calibration(&self, model_version: &str) -> Result<Option<String>, StoreError> {
        Ok(sqlx::query_scalar("SELECT calibration FROM site_calibrations WHERE model_version = $1")
            .bind(model_version)
            .fetch_optional(&self.pool)
            .await?)
    }

    /// Store `calibration` (JSON text) for `model_version`, replacing the one before.
    pub async fn set_site_calibration(&self, model_version: &str, calibration: &str) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO site_calibrations (model_version, calibration) VALUES ($1, $2) \
             ON CONFLICT (model_version) DO UPDATE SET calibration = excluded.calibration, created_at = excluded.created_at",
        )
        .bind(model_version)
        .bind(calibration)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Remove the site calibration of `model_version`; whether there was one.
    pub async fn clear_site_calibration(&self, model_version: &str) -> Result<bool, StoreError> {
        let done = sqlx::query("DELETE FROM site_calibrations WHERE model_version = $1").bind(model_version).execute(&self.pool).await?;
        Ok(done.rows_affected() > 0)
    }

    /// The stored liveness calibration of the liveness model `model` (its JSON text), if any.
    pub async fn liveness_calibration(&self, model: &str) -> Result<Option<String>, StoreError> {
        Ok(sqlx::query_scalar("SELECT calibration FROM liveness_calibrations WHERE model = $1")
            .bind(model)
            .fetch_optional(&self.pool)
            .await?)
    }

    /// Store `calibration` (JSON text) for the liveness model `model`, replacing the one before.
    pub async fn set_liveness_calibration(&self, model: &str, calibration: &str) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO liveness_calibrations (model, calibration) VALUES ($1, $2) \
             ON CONFLICT (model) DO UPDATE SET calibration = excluded.calibration, created_at = excluded.created_at",
        )
        .bind(model)
        .bind(calibration)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Remove the liveness calibration of `model`; whether there was one.
    pub async fn clear_liveness_calibration(&self, model: &str) -> Result<bool, StoreError> {
        let done = sqlx::query("DELETE FROM liveness_calibrations WHERE model = $1").bind(model).execute(&self.pool).await?;
        Ok(done.rows_affected() > 0)
    }
}
