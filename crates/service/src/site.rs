//! Site calibration: the thresholds raised to what a deployment's own photos need.
//!
//! A model's threshold tables are calibrated on other people's photos (LFW's news photos with IMM's
//! and ORL's lab photos). Where a deployment's photos come from one camera, one light and one
//! background, impostors look more alike than in that mix: the stated FMR 1e-3 came out 3.9e-3 on
//! lab photos of persons never used (docs/recognition.md). Yet impostor scores between a
//! deployment's own enrolled subjects predict its new persons' well: thresholds from the IMM and
//! ORL training persons' pairs held the stated rate on their held-out persons (0.6–1.1×).
//!
//! So a [`SiteCalibration`] is the threshold at each calibrated FMR on the impostor pairs of the
//! enrolled subjects (every pair of templates of two different subjects), kept where the pairs
//! are enough to show the rate ([`MIN_FALSE_MATCHES`]). It only ever *raises* a decision's
//! threshold ([`SiteCalibration::raise`]): by how far the site's threshold lies above the model's
//! one-template threshold at that FMR, for any enrolment size. A deployment whose impostors are
//! no more alike than the model's keeps the model's thresholds, and a gallery can make a decision
//! stricter, never looser.
//!
//! One person enrolled under two ids (by mistake, by a merge of two user bases, or on purpose by
//! whoever holds an enrolling key) makes genuine pairs look like impostors, and a few of those
//! would drag every threshold up to genuine scores. A pair of subjects with a template pair at or
//! above the model's duplicate threshold ([`duplicate_threshold`]: its impostor tail extrapolated a
//! decade past its 1e-4 point) is therefore suspected to be one person: its pairs are
//! left out and reported ([`SuspectedDuplicate`]). Every pair kept scores below that threshold, so
//! no count of enrolled look-alikes can raise a threshold past it.

use std::collections::HashMap;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use facegate_core::template::{OperatingPoint, Template};
use facegate_store::{Store, StoreError};
use facegate_vision::recognize::calibration::{CALIBRATED_FMRS, calibrated_points, threshold_at};

use crate::Matcher;

/// A site threshold is kept only where its impostor pairs allow at least this many false matches
/// at its FMR: fewer cannot place the rate (with 10 the threshold's FMR is within about ±30 %).
pub const MIN_FALSE_MATCHES: f64 = 10.0;

/// Templates a calibration pairs at most (all pairs of up to this many, about 18 M); a larger
/// gallery is sampled evenly ([`score_pairs`]).
pub const MAX_TEMPLATES: usize = 6_000;

/// Suspected duplicates listed in a calibration's JSON at most (the highest scores; the count of
/// pairs left out is always complete, and so is [`SiteCalibration::every_suspected_duplicate`]).
pub const MAX_LISTED_DUPLICATES: usize = 100;

/// Ids named per calibrated FMR as carrying its tail ([`Pull::tail_ids`]).
pub const MAX_TAIL_IDS: usize = 10;

/// How far a site threshold lies from the model's at one FMR, and which ids carry the impostor
/// pairs that put it there: the pull an operator checks before the service decides with it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pull {
    pub fmr: f64,
    /// The model's one-template threshold at `fmr`.
    pub model_threshold: f32,
    pub site_threshold: f32,
    /// `site_threshold − model_threshold`: what every decision's threshold at `fmr` rises by (none
    /// when it is not positive).
    pub raise: f32,
    /// Impostor pairs at or above the model's threshold; the model expects `fmr` × the pairs.
    pub tail_pairs: usize,
    pub expected_tail_pairs: f64,
    /// The ids in most of those pairs, most first (at most [`MAX_TAIL_IDS`]); never stored.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tail_ids: Vec<TailId>,
}

/// An enrolled id and the number of tail pairs it is in.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TailId {
    pub subject: String,
    pub pairs: usize,
}

/// One stated FMR's threshold on the site's impostor pairs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SitePoint {
    pub fmr: f64,
    pub threshold: f32,
}

/// Two enrolled ids whose templates score like one person's: left out of the impostor pairs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SuspectedDuplicate {
    pub subjects: [String; 2],
    /// Their best template pair's score.
    pub score: f32,
}

/// A deployment's own impostor thresholds for one model version (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SiteCalibration {
    pub model_version: String,
    /// Subjects and templates whose pairs were scored.
    pub subjects: usize,
    pub templates: usize,
    /// Impostor pairs scored (pairs of templates of two different subjects, suspected duplicates
    /// left out).
    pub impostor_pairs: usize,
    /// The calibrated FMRs the pairs allow, lowest threshold first.
    pub points: Vec<SitePoint>,
    /// The score at or above which two ids are taken for one person ([`duplicate_threshold`]);
    /// absent in calibrations stored before duplicates were looked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duplicate_threshold: Option<f32>,
    /// Template pairs left out because their two ids are suspected to be one person.
    #[serde(default)]
    pub duplicate_pairs_left_out: usize,
    /// The pairs of ids suspected to be one person, all of them (the list below stops at
    /// [`MAX_LISTED_DUPLICATES`]).
    #[serde(default)]
    pub duplicate_id_pairs: usize,
    /// The suspected pairs of ids, highest score first (at most [`MAX_LISTED_DUPLICATES`]); never
    /// stored ([`save`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub suspected_duplicates: Vec<SuspectedDuplicate>,
    /// Each calibrated FMR's pull against the model's threshold (empty when the model's thresholds
    /// were not given); stored without the ids.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pull: Vec<Pull>,
    /// Every suspected pair of ids, highest score first: for the operator's complete list
    /// (`facegate calibrate --duplicates-csv`); never serialised.
    #[serde(skip)]
    pub every_suspected_duplicate: Vec<SuspectedDuplicate>,
}

impl SiteCalibration {
    /// The thresholds of `pairs`' impostor scores at the calibrated FMRs their count allows, each
    /// with its pull against `model_points` (the model's one-template thresholds; none given, no
    /// pull). `names` gives each subject slot's id (for the suspected duplicates and the tails).
    pub fn from_pairs(
        model_version: &str,
        names: &[String],
        templates: usize,
        pairs: &PairScores,
        model_points: &[OperatingPoint],
    ) -> SiteCalibration {
        let impostor = &pairs.impostor;
        let points: Vec<SitePoint> = CALIBRATED_FMRS
            .iter()
            .filter(|&&fmr| impostor.len() as f64 * fmr >= MIN_FALSE_MATCHES)
            .map(|&fmr| SitePoint { fmr, threshold: threshold_at(impostor, fmr) })
            .collect();
        let name = |slot: u32| names.get(slot as usize).cloned().unwrap_or_else(|| slot.to_string());
        let mut suspected: Vec<SuspectedDuplicate> =
            pairs.duplicates.iter().map(|(&(a, b), &score)| SuspectedDuplicate { subjects: [name(a), name(b)], score }).collect();
        suspected.sort_by(|x, y| y.score.total_cmp(&x.score).then_with(|| x.subjects.cmp(&y.subjects)));
        let duplicate_id_pairs = suspected.len();
        let every_suspected_duplicate = suspected.clone();
        suspected.truncate(MAX_LISTED_DUPLICATES);
        let pull = points_pull(&points, model_points, impostor.len(), &pairs.tail, &name);
        SiteCalibration {
            model_version: model_version.to_string(),
            subjects: names.len(),
            templates,
            impostor_pairs: impostor.len(),
            points,
            duplicate_threshold: pairs.duplicate_threshold.is_finite().then_some(pairs.duplicate_threshold),
            duplicate_pairs_left_out: pairs.duplicate_pairs,
            duplicate_id_pairs,
            suspected_duplicates: suspected,
            pull,
            every_suspected_duplicate,
        }
    }

    /// What [`save`] keeps of it: the numbers, without any subject's id.
    pub fn as_stored(&self) -> SiteCalibration {
        let pull = self.pull.iter().map(|p| Pull { tail_ids: Vec::new(), ..p.clone() }).collect();
        SiteCalibration { suspected_duplicates: Vec::new(), every_suspected_duplicate: Vec::new(), pull, ..self.clone() }
    }

    /// The largest raise of a threshold, if any threshold rises.
    pub fn largest_raise(&self) -> Option<&Pull> {
        self.pull.iter().filter(|p| p.raise > 0.0).max_by(|a, b| a.raise.total_cmp(&b.raise))
    }

    /// `point` (the model's, for some enrolment size) raised by how far the site's threshold at
    /// its FMR lies above `one_template` (the model's one-template threshold at that FMR); unchanged
    /// where the site has no threshold there or its threshold is not above.
    pub fn raise(&self, point: OperatingPoint, one_template: f32) -> OperatingPoint {
        let site = self.points.iter().find(|p| p.fmr == point.fmr);
        match site {
            Some(site) if site.threshold > one_template => {
                OperatingPoint { threshold: point.threshold + (site.threshold - one_template), ..point }
            }
            _ => point,
        }
    }
}

/// Each site point's [`Pull`] against the model's point at its FMR: the tail pairs (impostor
/// pairs at or above the model's threshold, from `tail`) and the ids most often in them.
fn points_pull(
    points: &[SitePoint],
    model_points: &[OperatingPoint],
    impostor_pairs: usize,
    tail: &[(u32, u32, f32)],
    name: &dyn Fn(u32) -> String,
) -> Vec<Pull> {
    points
        .iter()
        .filter_map(|site| {
            let model = model_points.iter().find(|m| m.fmr == site.fmr)?;
            let mut per_id: HashMap<u32, usize> = HashMap::new();
            let mut tail_pairs = 0;
            for &(a, b, _) in tail.iter().filter(|t| t.2 >= model.threshold) {
                tail_pairs += 1;
                *per_id.entry(a).or_default() += 1;
                *per_id.entry(b).or_default() += 1;
            }
            let mut ids: Vec<(u32, usize)> = per_id.into_iter().collect();
            ids.sort_by(|x, y| y.1.cmp(&x.1).then_with(|| name(x.0).cmp(&name(y.0))));
            let tail_ids = ids.into_iter().take(MAX_TAIL_IDS).map(|(slot, pairs)| TailId { subject: name(slot), pairs }).collect();
            Some(Pull {
                fmr: site.fmr,
                model_threshold: model.threshold,
                site_threshold: site.threshold,
                raise: site.threshold - model.threshold,
                tail_pairs,
                expected_tail_pairs: site.fmr * impostor_pairs as f64,
                tail_ids,
            })
        })
        .collect()
}

/// The score at or above which two templates are taken for one person: the model's impostor tail
/// extrapolated one decade past its 1e-4 point (thresholds fall about linearly in log FMR), for a
/// subject of one template ([`extrapolated_duplicate_threshold`]).
pub fn duplicate_threshold(matcher: &dyn Matcher) -> f32 {
    extrapolated_duplicate_threshold(|fmr| matcher.operating_point(fmr, 1))
}

/// The step [`extrapolated_duplicate_threshold`] extends: from the 1e-3 point to the 1e-4 point.
/// Fixed rather than the table's lowest two, so the rule means the same for models calibrated
/// down to 1e-4 only and for those with a 1e-5 point (whose duplicates it would otherwise move).
const DUPLICATE_STEP: (f64, f64) = (1e-3, 1e-4);

/// [`duplicate_threshold`] of a one-template threshold table (`point`: the operating point closest
/// to an FMR). Infinite when the table lacks the 1e-3 or the 1e-4 point: then nothing is suspected.
pub fn extrapolated_duplicate_threshold(point: impl Fn(f64) -> OperatingPoint) -> f32 {
    let (next, lowest) = DUPLICATE_STEP;
    let (at_lowest, at_next) = (point(lowest), point(next));
    let decade = at_lowest.threshold - at_next.threshold;
    if at_lowest.fmr != lowest || at_next.fmr != next || !decade.is_finite() {
        return f32::INFINITY;
    }
    at_lowest.threshold + decade.max(0.0)
}

/// A site's template pairs of two different subjects, split into the impostor scores a
/// calibration counts and the pairs of subjects suspected to be one person.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PairScores {
    /// Cosines of the pairs of subjects not suspected.
    pub impostor: Vec<f32>,
    /// Each suspected pair of subject slots (lower first) with its best template pair's score.
    pub duplicates: HashMap<(u32, u32), f32>,
    /// Template pairs of the suspected subjects, left out of `impostor`.
    pub duplicate_pairs: usize,
    pub duplicate_threshold: f32,
    /// The impostor pairs (suspected ones left out) at or above the `tail_from` asked for: their
    /// subject slots (lower first) and score, what [`SiteCalibration::pull`] names.
    pub tail: Vec<(u32, u32, f32)>,
}

/// Score every pair of rows of different subjects: `rows` are unit vectors (`dimension` each)
/// with `owners` their subject slots. With more than [`MAX_TEMPLATES`] rows, every n-th row is
/// taken (rows in subject order spread the sample over the subjects) and those are paired. The
/// pairs of subjects with a template pair at or above `duplicate_threshold` are suspected, and
/// every score of theirs left out; the impostor pairs kept at or above `tail_from` are listed.
pub fn score_pairs(rows: &[f32], dimension: usize, owners: &[u32], duplicate_threshold: f32, tail_from: f32) -> PairScores {
    let count = owners.len();
    let step = count.div_ceil(MAX_TEMPLATES).max(1);
    let taken: Vec<usize> = (0..count).step_by(step).collect();
    let row = |i: usize| &rows[i * dimension..(i + 1) * dimension];
    // The pairs of rows of two subjects, always in the same order, with their subjects' slots.
    let pairs = || {
        taken
            .iter()
            .enumerate()
            .flat_map(|(a, &i)| taken[a + 1..].iter().map(move |&j| (i, j)))
            .filter(|&(i, j)| owners[i] != owners[j])
            .map(|(i, j)| (i, j, (owners[i].min(owners[j]), owners[i].max(owners[j]))))
    };
    // Each pair scored once; the scores of the suspected subjects' pairs are then dropped by a
    // second walk of the same order, which computes nothing.
    let mut impostor: Vec<f32> = pairs().map(|(i, j, _)| facegate_core::vector::dot(row(i), row(j))).collect();
    let mut duplicates: HashMap<(u32, u32), f32> = HashMap::new();
    let mut tail: Vec<(u32, u32, f32)> = Vec::new();
    for ((_, _, slots), &score) in pairs().zip(&impostor) {
        if score >= duplicate_threshold {
            let best = duplicates.entry(slots).or_insert(score);
            *best = best.max(score);
        }
        if score >= tail_from {
            tail.push((slots.0, slots.1, score));
        }
    }
    // The tail is of the pairs kept: none of the suspected subjects'.
    tail.retain(|&(a, b, _)| !duplicates.contains_key(&(a, b)));
    let scored = impostor.len();
    if !duplicates.is_empty() {
        let mut walk = pairs();
        impostor.retain(|_| walk.next().is_some_and(|(_, _, slots)| !duplicates.contains_key(&slots)));
    }
    let duplicate_pairs = scored - impostor.len();
    PairScores { impostor, duplicates, duplicate_pairs, duplicate_threshold, tail }
}

/// Rows of unit vectors with their subject slots and the subjects' ids, as a calibration reads
/// them from a gallery: the rows of one dimension (a model version has one).
#[derive(Debug, Clone, Default)]
pub struct SiteRows {
    pub values: Vec<f32>,
    pub owners: Vec<u32>,
    pub dimension: usize,
    pub names: Vec<String>,
}

impl SiteRows {
    /// Add one subject's template vectors (a vector of another dimension than the first is no
    /// pair to score, and is skipped).
    pub fn push_subject<'a>(&mut self, name: &str, vectors: impl IntoIterator<Item = &'a [f32]>) {
        let slot = self.names.len() as u32;
        for v in vectors {
            if self.dimension != 0 && v.len() != self.dimension {
                continue;
            }
            self.dimension = v.len();
            self.values.extend_from_slice(v);
            self.owners.push(slot);
        }
        self.names.push(name.to_string());
    }

    /// The site calibration of these rows for `model_version` (module docs), with its pull
    /// against `model_points` (the model's one-template thresholds at the calibrated FMRs).
    pub fn calibrate(&self, model_version: &str, duplicate_threshold: f32, model_points: &[OperatingPoint]) -> SiteCalibration {
        let tail_from = model_points.iter().map(|p| p.threshold).fold(f32::INFINITY, f32::min);
        let pairs = score_pairs(&self.values, self.dimension, &self.owners, duplicate_threshold, tail_from);
        SiteCalibration::from_pairs(model_version, &self.names, self.owners.len(), &pairs, model_points)
    }
}

/// The site calibration of `matcher`'s model version measured on the enrolled subjects' templates
/// in `store` (sealed ones opened with its key). A subject whose templates cannot be read is an
/// error: a calibration must not silently leave subjects out.
pub async fn measure(store: &Store, matcher: &dyn Matcher) -> Result<SiteCalibration, StoreError> {
    let version = matcher.model_version().to_string();
    let read = store
        .gallery(&version, (SiteRows::default(), None), |(rows, error): &mut (SiteRows, Option<StoreError>), subject, templates| {
            match templates {
                Ok(templates) => rows.push_subject(subject, templates.iter().map(|t| t.vector.as_slice())),
                Err(e) => {
                    error.get_or_insert(e);
                }
            }
        })
        .await?;
    match read {
        (_, Some(e)) => Err(e),
        (rows, None) => Ok(rows.calibrate(&version, duplicate_threshold(matcher), &model_points(matcher))),
    }
}

/// `matcher`'s one-template operating points at the calibrated FMRs it has.
pub fn model_points(matcher: &dyn Matcher) -> Vec<OperatingPoint> {
    calibrated_points(|fmr| matcher.operating_point(fmr, 1))
}

/// Store `calibration` for its model version, replacing the one before. The suspected duplicates'
/// and the tails' ids are the operator's to act on, not kept: a stored calibration names no
/// subject, so erasing one leaves nothing of it here.
pub async fn save(store: &Store, calibration: &SiteCalibration) -> Result<(), StoreError> {
    let kept = calibration.as_stored();
    let json = serde_json::to_string(&kept).map_err(|e| StoreError::Refused(e.to_string()))?;
    store.set_site_calibration(&calibration.model_version, &json).await
}

/// What a matcher decides with, given the store's site calibration of its model version.
#[derive(Debug, Clone, PartialEq)]
pub enum SiteStatus {
    /// No site calibration is stored for the model version: the model's thresholds.
    None,
    /// The stored calibration raises the model's thresholds.
    InUse(Arc<SiteCalibration>),
    /// One is stored, but the matcher's score is no best cosine (the classical recognizer), so
    /// the site's pair cosines say nothing of its thresholds: the model's.
    NotForThisMatcher,
}

impl SiteStatus {
    pub fn calibration(&self) -> Option<&Arc<SiteCalibration>> {
        match self {
            SiteStatus::InUse(site) => Some(site),
            _ => None,
        }
    }
}

/// The stored site calibration of `matcher`'s model version, if it applies to that matcher.
pub async fn load(store: &Store, matcher: &dyn Matcher) -> Result<SiteStatus, StoreError> {
    let version = matcher.model_version();
    let Some(json) = store.site_calibration(version).await? else {
        return Ok(SiteStatus::None);
    };
    let site: SiteCalibration =
        serde_json::from_str(&json).map_err(|e| StoreError::Refused(format!("the site calibration of {version} is unreadable: {e}")))?;
    Ok(if matcher.max_cosine_scoring() { SiteStatus::InUse(Arc::new(site)) } else { SiteStatus::NotForThisMatcher })
}

/// A matcher with its operating points raised by the site calibration in use: what the service
/// decides with. Scores and model version are the inner matcher's.
pub struct CalibratedMatcher<M: ?Sized> {
    pub site: Option<Arc<SiteCalibration>>,
    pub inner: Arc<M>,
}

// Not derived: a derive would ask `M: Clone`, which a trait object is not.
impl<M: ?Sized> Clone for CalibratedMatcher<M> {
    fn clone(&self) -> Self {
        CalibratedMatcher { site: self.site.clone(), inner: self.inner.clone() }
    }
}

impl<M: Matcher + ?Sized> Matcher for CalibratedMatcher<M> {
    fn model_version(&self) -> &str {
        self.inner.model_version()
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        self.inner.score(probe, enrolled)
    }
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        let point = self.inner.operating_point(fmr, enrolled);
        match &self.site {
            Some(site) => site.raise(point, self.inner.operating_point(point.fmr, 1).threshold),
            None => point,
        }
    }
    fn max_cosine_scoring(&self) -> bool {
        self.inner.max_cosine_scoring()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn site(points: &[(f64, f32)]) -> SiteCalibration {
        SiteCalibration {
            model_version: "m".into(),
            subjects: 0,
            templates: 0,
            impostor_pairs: 0,
            points: points.iter().map(|&(fmr, threshold)| SitePoint { fmr, threshold }).collect(),
            duplicate_threshold: None,
            duplicate_pairs_left_out: 0,
            duplicate_id_pairs: 0,
            suspected_duplicates: Vec::new(),
            pull: Vec::new(),
            every_suspected_duplicate: Vec::new(),
        }
    }

    #[test]
    fn a_site_raises_thresholds_by_its_margin_and_never_lowers_them() {
        let s = site(&[(1e-2, 0.80), (1e-3, 0.70)]);
        // 1e-2: the site's 0.80 is 0.05 above the model's one-template 0.75; a five-template
        // threshold of 0.78 moves by the same.
        let raised = s.raise(OperatingPoint { fmr: 1e-2, threshold: 0.78 }, 0.75);
        assert!((raised.threshold - 0.83).abs() < 1e-6 && raised.fmr == 1e-2);
        // 1e-3: the site's threshold is below the model's: unchanged.
        assert_eq!(s.raise(OperatingPoint { fmr: 1e-3, threshold: 0.8 }, 0.8).threshold, 0.8);
        // 1e-4: the site's pairs did not allow it: unchanged.
        assert_eq!(s.raise(OperatingPoint { fmr: 1e-4, threshold: 0.9 }, 0.9).threshold, 0.9);
    }

    #[test]
    fn only_the_rates_the_pairs_can_show_are_kept() {
        let scores: Vec<f32> = (0..2_000).map(|i| i as f32 / 2_000.0).collect();
        let pairs = PairScores { impostor: scores.clone(), duplicate_threshold: f32::INFINITY, ..PairScores::default() };
        let names: Vec<String> = (0..50).map(|i| i.to_string()).collect();
        let s = SiteCalibration::from_pairs("m", &names, 100, &pairs, &[]);
        // 2,000 pairs: 20 false matches at 1e-2, 2 at 1e-3.
        assert_eq!(s.points.len(), 1);
        assert_eq!(s.points[0].fmr, 1e-2);
        let above = scores.iter().filter(|&&v| v >= s.points[0].threshold).count();
        assert_eq!(above, 20, "the lowest threshold with 1 % of the pairs at or above");
        assert_eq!((s.subjects, s.templates, s.duplicate_threshold), (50, 100, None));
    }

    #[test]
    fn impostor_pairs_are_the_pairs_of_different_subjects() {
        // Three rows: two of subject 0 (identical), one of subject 1.
        let rows = [1.0, 0.0, 1.0, 0.0, 0.6, 0.8];
        let mut pairs = score_pairs(&rows, 2, &[0, 0, 1], f32::INFINITY, f32::INFINITY);
        pairs.impostor.sort_by(f32::total_cmp);
        assert_eq!(pairs.impostor, [0.6, 0.6]);
        assert!(pairs.duplicates.is_empty());
    }

    #[test]
    fn ids_that_score_like_one_person_are_left_out_and_named() {
        // Subjects a and c hold the same face (one template each, c's twice); b is someone else.
        let mut rows = SiteRows::default();
        rows.push_subject("a", [&[1.0f32, 0.0][..]]);
        rows.push_subject("b", [&[0.6f32, 0.8][..]]);
        rows.push_subject("c", [&[1.0f32, 0.0][..], &[0.995f32, 0.0998][..]]);
        let s = rows.calibrate("m", 0.9, &[]);
        assert_eq!(s.duplicate_pairs_left_out, 2, "both of c's templates against a's");
        assert_eq!(s.impostor_pairs, 3, "a-b, b-c twice");
        assert_eq!(s.suspected_duplicates, [SuspectedDuplicate { subjects: ["a".into(), "c".into()], score: 1.0 }]);
        assert_eq!(s.duplicate_threshold, Some(0.9));
        // Without the threshold every pair counts.
        assert_eq!(rows.calibrate("m", f32::INFINITY, &[]).impostor_pairs, 5);
    }

    #[test]
    fn one_photo_under_many_ids_cannot_raise_a_threshold() {
        // 114 ids of one face and 40 different faces: the copies are suspected, the rest calibrate.
        let mut rows = SiteRows::default();
        for i in 0..114 {
            rows.push_subject(&format!("copy{i}"), [&[1.0f32, 0.0, 0.0][..]]);
        }
        for i in 0..40 {
            let angle = 0.5 + i as f32 * 0.05;
            rows.push_subject(&format!("other{i}"), [&[0.0f32, angle.cos(), angle.sin()][..]]);
        }
        let s = rows.calibrate("m", 0.999, &[]);
        assert_eq!(s.duplicate_pairs_left_out, 114 * 113 / 2);
        assert!(s.points.iter().all(|p| p.threshold < 0.999), "{:?}", s.points);
        assert_eq!(s.suspected_duplicates.len(), MAX_LISTED_DUPLICATES);
        // The count is of every pair, not of those listed; the complete list has them all.
        assert_eq!(s.duplicate_id_pairs, 114 * 113 / 2);
        assert_eq!(s.every_suspected_duplicate.len(), 114 * 113 / 2);
    }

    #[test]
    fn the_pull_names_the_ids_whose_pairs_carry_the_tail() {
        // 42 subjects around a circle (no two closer than cosine 0.990) and 8 ids ("near0".."near7")
        // of faces close to one another (cosine 0.9975-0.99995), below the duplicate threshold:
        // their 28 pairs carry the tail above the model's 0.995 at 1e-2.
        let mut rows = SiteRows::default();
        for i in 0..42 {
            let angle = i as f32 * 0.14;
            rows.push_subject(&format!("s{i}"), [&[angle.cos(), angle.sin(), 0.0][..]]);
        }
        for i in 0..8 {
            let angle = 0.01 * i as f32;
            rows.push_subject(&format!("near{i}"), [&[0.0f32, angle.sin(), angle.cos()][..]]);
        }
        let model = [OperatingPoint { fmr: 1e-2, threshold: 0.995 }, OperatingPoint { fmr: 1e-3, threshold: 0.999 }];
        let s = rows.calibrate("m", 0.99999, &model);
        assert_eq!((s.duplicate_id_pairs, s.impostor_pairs), (0, 50 * 49 / 2));
        assert_eq!(s.pull.len(), 1, "1,225 pairs calibrate 1e-2 only: {:?}", s.pull);
        let pull = &s.pull[0];
        assert_eq!((pull.fmr, pull.model_threshold, pull.tail_pairs), (1e-2, 0.995, 28), "{pull:?}");
        assert!((pull.expected_tail_pairs - 12.25).abs() < 1e-9);
        assert!(pull.raise > 0.0 && (pull.raise - (pull.site_threshold - 0.995)).abs() < 1e-6, "{pull:?}");
        assert_eq!(pull.tail_ids.len(), 8, "{pull:?}");
        assert!(pull.tail_ids.iter().all(|t| t.subject.starts_with("near") && t.pairs == 7), "{pull:?}");
        assert_eq!(s.largest_raise().map(|p| p.fmr), Some(1e-2));
    }

    #[test]
    fn a_large_gallery_is_sampled_evenly() {
        let count = 2 * MAX_TEMPLATES + 1;
        let rows: Vec<f32> = (0..count).flat_map(|i| [(i as f32).cos(), (i as f32).sin()]).collect();
        let owners: Vec<u32> = (0..count as u32).collect();
        let taken = count.div_ceil(3);
        assert_eq!(score_pairs(&rows, 2, &owners, f32::INFINITY, f32::INFINITY).impostor.len(), taken * (taken - 1) / 2);
    }

    #[test]
    fn the_duplicate_threshold_extrapolates_the_models_tail_a_decade() {
        /// Thresholds 0.70, 0.75, 0.79 at 1e-2 … 1e-4, and at 1e-5 when given; asked for a rate it
        /// lacks, the closest point answers, as a calibration's does.
        struct Table(Option<f32>);
        impl Matcher for Table {
            fn model_version(&self) -> &str {
                "m"
            }
            fn score(&self, _: &facegate_core::Template, _: &[facegate_core::Template]) -> f32 {
                0.0
            }
            fn operating_point(&self, fmr: f64, _: usize) -> OperatingPoint {
                match (fmr, self.0) {
                    (f, _) if f >= 1e-2 => OperatingPoint { fmr: 1e-2, threshold: 0.70 },
                    (f, _) if f >= 1e-3 => OperatingPoint { fmr: 1e-3, threshold: 0.75 },
                    (f, Some(threshold)) if f < 1e-4 => OperatingPoint { fmr: 1e-5, threshold },
                    _ => OperatingPoint { fmr: 1e-4, threshold: 0.79 },
                }
            }
        }
        assert!((duplicate_threshold(&Table(None)) - 0.83).abs() < 1e-6);
        // A 1e-5 point does not move it: the rule extends the 1e-3 → 1e-4 step for every model.
        assert!((duplicate_threshold(&Table(Some(0.82))) - 0.83).abs() < 1e-6);
    }
}
