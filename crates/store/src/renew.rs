//! Renewing protected templates (`facegate renew-protection`): every stored template of the model
//! versions a renewal takes is rewritten, vector and model version, with the site calibrations of
//! those versions carried over, in ONE transaction. Either the whole database is renewed or
//! nothing is: a crash or an error midway leaves the old templates as they were, and running the
//! command again starts over. Sealed subjects stay sealed under their own data key (the vector
//! is sealed again, since the model version is part of what the seal authenticates).
//!
//! What a template becomes is the caller's (`facegate_service::protection::Renewal`): the store
//! hands each vector over and stores what comes back; it knows nothing of rotations.

use serde::Serialize;
use sqlx::Row;

use facegate_core::template::Template;

use crate::codec::{Sealing, encode_vector, open_vector};
use crate::{ACQUIRE_TIMEOUT, Store, StoreError};

/// Templates rewritten per query: the rows are read a batch at a time, never all at once.
const BATCH: i64 = 1024;

/// One model version renewed.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct RenewedVersion {
    pub from: String,
    pub to: String,
    pub templates: u64,
    /// Whether its site calibration was carried over.
    pub calibration: bool,
}

/// What [`Store::renew_templates`] did.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct RenewReport {
    /// Subjects whose templates were rewritten.
    pub subjects: u64,
    pub templates: u64,
    pub versions: Vec<RenewedVersion>,
}

/// How a renewal rewrites a database: the new model version of a stored one (`None`: left as it
/// is), a template's new vector, and a site calibration's new JSON text for its new version.
pub trait Renewing: Send {
    fn version(&self, stored: &str) -> Option<String>;
    fn vector(&mut self, stored: &[f32]) -> Vec<f32>;
    fn calibration(&self, json: &str, to: &str) -> Result<String, String>;
}

impl Store {
    /// Rewrite every template of the versions `renewing` takes, and move their site calibrations
    /// to the new versions, in one transaction (module docs). A database holding none of them
    /// is left as it is (an empty report): running a finished renewal again changes nothing.
    pub async fn renew_templates(&self, renewing: &mut dyn Renewing) -> Result<RenewReport, StoreError> {
        let mut tx = self.begin_write(tokio::time::Instant::now() + ACQUIRE_TIMEOUT).await?;
        // A write first, so the transaction holds SQLite's write lock from its start.
        sqlx::query("UPDATE templates SET model_version = model_version WHERE id < 0").execute(&mut *tx).await?;
        let stored: Vec<String> =
            sqlx::query_scalar("SELECT DISTINCT model_version FROM templates UNION SELECT model_version FROM site_calibrations ORDER BY 1")
                .fetch_all(&mut *tx)
                .await?;
        let mut report = RenewReport::default();
        let mut subjects: Vec<String> = Vec::new();
        for from in stored {
            let Some(to) = renewing.version(&from) else { continue };
            let templates = self.renew_version(&mut tx, renewing, &from, &to, &mut subjects).await?;
            let calibration = move_calibration(&mut tx, renewing, &from, &to).await?;
            report.templates += templates;
            report.versions.push(RenewedVersion { from, to, templates, calibration });
        }
        subjects.sort();
        subjects.dedup();
        for subject in &subjects {
            self.record_change(&mut tx, subject).await?;
        }
        report.subjects = subjects.len() as u64;
        tx.commit().await.map_err(StoreError::of_commit)?;
        Ok(report)
    }

    /// Every template of `from` rewritten as `to`, a batch at a time (a rewritten row leaves
    /// `from`, so each batch is the next); returns how many, and adds their subjects to `subjects`.
    async fn renew_version(
        &self,
        tx: &mut sqlx::AnyConnection,
        renewing: &mut dyn Renewing,
        from: &str,
        to: &str,
        subjects: &mut Vec<String>,
    ) -> Result<u64, StoreError> {
        let mut renewed = 0u64;
        loop {
            let rows = sqlx::query(
                "SELECT t.id, t.subject_id, t.dimension, t.vector, s.key_id, s.data_key
                 FROM templates t JOIN subjects s ON s.id = t.subject_id
                 WHERE t.model_version = $1 ORDER BY t.subject_id, t.id LIMIT $2",
            )
            .bind(from)
            .bind(BATCH)
            .fetch_all(&mut *tx)
            .await?;
            if rows.is_empty() {
                return Ok(renewed);
            }
            // The data key of the subject before, kept while its rows follow.
            let mut current: Option<(String, Sealing)> = None;
            for row in &rows {
                let (id, subject): (i64, String) = (row.try_get("id")?, row.try_get("subject_id")?);
                if current.as_ref().is_none_or(|(s, _)| *s != subject) {
                    let sealing = self.sealing(&subject, row.try_get("key_id")?, row.try_get("data_key")?)?;
                    subjects.push(subject.clone());
                    current = Some((subject.clone(), sealing));
                }
                let (_, sealing) = current.as_ref().expect("set above");
                let blob: Vec<u8> = row.try_get("vector")?;
                let old = open_vector(sealing, &subject, id, row.try_get("dimension")?, from.to_string(), &blob)?;
                let new = Template { model_version: to.to_string(), vector: renewing.vector(&old.vector) };
                if new.vector.len() != old.vector.len() {
                    return Err(StoreError::Refused(format!("template {id}: the renewal changed its length")));
                }
                sqlx::query("UPDATE templates SET model_version = $2, vector = $3 WHERE id = $1")
                    .bind(id)
                    .bind(to)
                    .bind(encode_vector(sealing, &subject, &new))
                    .execute(&mut *tx)
                    .await?;
                renewed += 1;
            }
        }
    }
}

/// The site calibration of `from`, if any, stored for `to` (its text rewritten by `renewing`) in
/// place of any there was, and removed from `from`; whether there was one.
async fn move_calibration(tx: &mut sqlx::AnyConnection, renewing: &dyn Renewing, from: &str, to: &str) -> Result<bool, StoreError> {
    let Some(json): Option<String> = sqlx::query_scalar("SELECT calibration FROM site_calibrations WHERE model_version = $1")
        .bind(from)
        .fetch_optional(&mut *tx)
        .await?
    else {
        return Ok(false);
    };
    let renewed = renewing.calibration(&json, to).map_err(|e| StoreError::Refused(format!("the site calibration of {from}: {e}")))?;
    sqlx::query(
        "INSERT INTO site_calibrations (model_version, calibration) VALUES ($1, $2) \
         ON CONFLICT (model_version) DO UPDATE SET calibration = excluded.calibration, created_at = excluded.created_at",
    )
    .bind(to)
    .bind(renewed)
    .execute(&mut *tx)
    .await?;
    sqlx::query("DELETE FROM site_calibrations WHERE model_version = $1").bind(from).execute(&mut *tx).await?;
    Ok(true)
}

#[cfg(test)]
mod tests {
    use facegate_core::SubjectId;
    use facegate_core::template::Template;

    use super::Renewing;
    use crate::{KeyRing, Store};

    const K1: &str = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";

    /// `old` → `new`, every value negated; a calibration's text gets a mark (or is refused).
    struct Negate {
        refuse_calibration: bool,
    }

    impl Renewing for Negate {
        fn version(&self, stored: &str) -> Option<String> {
            (stored == "m+rot-old").then(|| "m+rot-new".to_string())
        }
        fn vector(&mut self, stored: &[f32]) -> Vec<f32> {
            stored.iter().map(|v| -v).collect()
        }
        fn calibration(&self, json: &str, to: &str) -> Result<String, String> {
            if self.refuse_calibration { Err("refused".into()) } else { Ok(format!("{json} for {to}")) }
        }
    }

    fn t(version: &str, seed: f32) -> Template {
        Template { model_version: version.into(), vector: (0..8).map(|i| seed + i as f32).collect() }
    }

    #[tokio::test]
    async fn a_renewal_rewrites_every_template_of_its_versions_in_one_transaction() {
        let dir = std::env::temp_dir().join(format!("facegate-renew-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let url = format!("sqlite://{}", dir.join("r.db").display());
        let store = Store::connect(&url, Some(KeyRing::parse(K1).unwrap())).await.unwrap();
        let (a, b) = (SubjectId::parse("a").unwrap(), SubjectId::parse("b").unwrap());
        store.enroll(&a, &[t("m+rot-old", 1.0), t("other", 2.0)]).await.unwrap();
        store.enroll(&b, &[t("m+rot-old", 3.0), t("m+rot-old", 4.0)]).await.unwrap();
        store.set_site_calibration("m+rot-old", "cal").await.unwrap();

        // A refusal midway (the calibration comes after the templates) leaves everything as it was.
        assert!(store.renew_templates(&mut Negate { refuse_calibration: true }).await.is_err());
        assert_eq!(store.templates(&a).await.unwrap().unwrap(), vec![t("m+rot-old", 1.0), t("other", 2.0)]);
        assert_eq!(store.site_calibration("m+rot-old").await.unwrap().as_deref(), Some("cal"));

        let report = store.renew_templates(&mut Negate { refuse_calibration: false }).await.unwrap();
        assert_eq!((report.subjects, report.templates, report.versions.len()), (2, 3, 1), "{report:?}");
        assert!(report.versions[0].calibration);
        let negated = |seed: f32| Template { model_version: "m+rot-new".into(), vector: t("", seed).vector.iter().map(|v| -v).collect() };
        // Sealed subjects read back (sealed again under the new version), other versions untouched.
        assert_eq!(store.templates(&a).await.unwrap().unwrap(), vec![negated(1.0), t("other", 2.0)]);
        assert_eq!(store.templates(&b).await.unwrap().unwrap(), vec![negated(3.0), negated(4.0)]);
        assert_eq!(store.site_calibration("m+rot-old").await.unwrap(), None);
        assert_eq!(store.site_calibration("m+rot-new").await.unwrap().as_deref(), Some("cal for m+rot-new"));
        // Done once: a second run finds nothing to renew.
        let again = store.renew_templates(&mut Negate { refuse_calibration: false }).await.unwrap();
        assert_eq!((again.subjects, again.templates), (0, 0));
        assert_eq!(store.templates(&b).await.unwrap().unwrap(), vec![negated(3.0), negated(4.0)]);
        store.close().await;
        let _ = std::fs::remove_dir_all(&dir);
    }
}
