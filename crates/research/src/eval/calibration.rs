//! Does the stated false match rate hold on every kind of photo? A recognizer's thresholds are
//! calibrated on some persons and checked on others, per photo domain: LFW's news photos (the
//! wild) and IMM's and ORL's lab photos. Candidates: the raw cosine calibrated as the models ship
//! it (LFW calibration persons with the IMM and ORL held-out persons, so the lab check there is on
//! the calibration persons themselves), the raw cosine calibrated on persons disjoint from every
//! checked one (LFW calibration persons with the IMM and ORL *training* persons), and cohort score
//! normalisation (S-norm, AS-norm) against the training persons, calibrated the disjoint way, and
//! the model's thresholds raised by a site calibration on each checked set's own other persons
//! (what `facegate calibrate` does with a deployment's enrolled subjects).

use serde::Serialize;

use super::protocol::all_pairs_by;
use crate::dataset::Split;
use crate::train_deep::{Sample, Set};
use facegate_core::vector::dot;
use facegate_service::site::{self, SiteCalibration, SiteRows};
use facegate_vision::recognize::Calibration;
use facegate_vision::recognize::calibration::{CALIBRATED_FMRS, calibrated_points};
use facegate_vision::recognize::score_norm::{Cohort, CohortStats, s_norm};

/// How a comparison is scored.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum Scoring {
    Cosine,
    /// The cosine, with a threshold table per probe domain (grey or colour photo).
    CosineByProbeDomain,
    /// The cosine, the model's thresholds raised by a site calibration on the checked set's own
    /// other persons (`facegate calibrate`, [`SiteCalibration`]).
    CosineWithSiteCalibration,
    /// S-norm (`top_k` 0) or AS-norm over the `top_k` most similar cohort members.
    CohortNorm {
        top_k: usize,
    },
}

/// Which persons set the thresholds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum CalibrationPersons {
    /// LFW calibration persons and the IMM/ORL held-out persons (as `train deep`/`train embedding` do).
    Shipped,
    /// LFW calibration persons and the IMM/ORL training persons: disjoint from every checked set.
    Disjoint,
}

impl CalibrationPersons {
    pub fn takes(self, s: &Sample) -> bool {
        match (self, s.set) {
            (_, Set::Lfw) => s.split == Split::Calibration,
            (CalibrationPersons::Shipped, _) => s.split == Split::Test,
            (CalibrationPersons::Disjoint, _) => s.split == Split::Train,
        }
    }
}

/// The FMR observed at one stated operating point on one set.
#[derive(Debug, Clone, Serialize)]
pub struct Observed {
    pub set: &'static str,
    pub stated: f64,
    pub observed: f64,
    pub false_matches: usize,
    pub impostors: usize,
    /// FNMR at the same threshold.
    pub fnmr: f64,
    /// observed / stated lies in 0.5–2 (on a set too small to show the rate: no more false
    /// matches than twice the rate allows, at least one).
    pub holds: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct CandidateReport {
    pub scoring: Scoring,
    pub calibration: CalibrationPersons,
    pub rows: Vec<Observed>,
}

/// Each checked set's site: the persons a deployment of such photos would have enrolled before
/// the checked ones, disjoint from them (LFW's calibration persons; the IMM and ORL training
/// persons; both).
pub fn sites() -> [fn(&Sample) -> bool; 3] {
    [
        |s| s.set == Set::Lfw && s.split == Split::Calibration,
        |s| s.set != Set::Lfw && s.split == Split::Train,
        |s| CalibrationPersons::Disjoint.takes(s),
    ]
}

/// The checked sets: LFW test persons, IMM and ORL held-out persons, and both pooled.
pub fn checked_sets() -> [(&'static str, fn(&Sample) -> bool); 3] {
    [
        ("LFW test persons", |s| s.set == Set::Lfw && s.split == Split::Test),
        ("IMM + ORL held-out", |s| s.set != Set::Lfw && s.split == Split::Test),
        ("pooled", |s| s.split == Split::Test),
    ]
}

/// Every sample's cohort statistics (`None`: no template), against a cohort of the training
/// persons' templates (every `stride`-th, all sets).
pub fn cohort_stats(samples: &[Sample], templates: &[Option<Vec<f32>>], top_k: usize, stride: usize) -> Vec<Option<CohortStats>> {
    let members: Vec<Vec<f32>> = samples
        .iter()
        .zip(templates)
        .filter(|(s, _)| s.split == Split::Train)
        .filter_map(|(_, t)| t.clone())
        .step_by(stride.max(1))
        .collect();
    let dims = members.first().map_or(0, Vec::len);
    let cohort = Cohort::new(dims, &members, top_k);
    crate::par_map(templates, 2, |t| t.as_ref().map(|t| cohort.stats(t)))
}

/// The samples `keep` takes that have a template: index, label, template.
fn kept<'a>(samples: &'a [Sample], templates: &'a [Option<Vec<f32>>], keep: &dyn Fn(&Sample) -> bool) -> Vec<(usize, &'a str, &'a [f32])> {
    samples
        .iter()
        .zip(templates)
        .enumerate()
        .filter(|(_, (s, _))| keep(s))
        .filter_map(|(i, (s, t))| t.as_deref().map(|t| (i, s.label.as_str(), t)))
        .collect()
}

/// The service's site calibration of `site`'s templates, each person one enrolled subject.
fn site_calibration(site: &[(usize, &str, &[f32])], duplicate_threshold: f32) -> SiteCalibration {
    let mut persons: Vec<(&str, Vec<&[f32]>)> = Vec::new();
    let mut slots: std::collections::HashMap<&str, usize> = std::collections::HashMap::new();
    for &(_, label, template) in site {
        let slot = *slots.entry(label).or_insert_with(|| {
            persons.push((label, Vec::new()));
            persons.len() - 1
        });
        persons[slot].1.push(template);
    }
    let mut rows = SiteRows::default();
    for (label, templates) in persons {
        rows.push_subject(label, templates);
    }
    rows.calibrate("research", duplicate_threshold, &[])
}

/// Genuine and impostor scores of every pair of the samples `keep` takes.
fn pair_scores(
    samples: &[Sample],
    templates: &[Option<Vec<f32>>],
    stats: Option<&[Option<CohortStats>]>,
    keep: &dyn Fn(&Sample) -> bool,
) -> (Vec<f32>, Vec<f32>) {
    let items = kept(samples, templates, keep);
    let labels: Vec<&str> = items.iter().map(|(_, l, _)| *l).collect();
    all_pairs_by(&labels, &|a, b| {
        let raw = dot(items[a].2, items[b].2);
        match stats {
            None => raw,
            Some(st) => match (st[items[a].0], st[items[b].0]) {
                (Some(x), Some(y)) => s_norm(raw, x, y),
                _ => raw,
            },
        }
    })
}

/// One candidate: thresholds from the calibration persons, FMR and FNMR observed on each checked set.
pub fn report(
    samples: &[Sample],
    templates: &[Option<Vec<f32>>],
    scoring: Scoring,
    stats: Option<&[Option<CohortStats>]>,
    calibration: CalibrationPersons,
) -> CandidateReport {
    let (g, i) = pair_scores(samples, templates, stats, &|s| calibration.takes(s));
    let table = Calibration::from_scores(&g, &i, &CALIBRATED_FMRS, "calibration persons");
    let mut rows = Vec::new();
    for (set, keep) in checked_sets() {
        let (g, i) = pair_scores(samples, templates, stats, &keep);
        for &fmr in &CALIBRATED_FMRS {
            rows.push(observed(set, fmr, &g, &i, table.operating_point(fmr).threshold));
        }
    }
    CandidateReport { scoring, calibration, rows }
}

/// One threshold check of a set: observed FMR and FNMR at `threshold` (per stated FMR).
fn observed(set: &'static str, fmr: f64, genuine: &[f32], impostor: &[f32], threshold: f32) -> Observed {
    let false_matches = impostor.iter().filter(|&&s| s >= threshold).count();
    let observed = false_matches as f64 / impostor.len().max(1) as f64;
    let fnmr = genuine.iter().filter(|&&s| s < threshold).count() as f64 / genuine.len().max(1) as f64;
    let holds = holds(fmr, false_matches, impostor.len());
    Observed { set, stated: fmr, observed, false_matches, impostors: impostor.len(), fnmr, holds }
}

/// Does `false_matches` of `impostors` hold the stated `fmr` (0.5–2×)? A set of fewer than 1/fmr
/// impostor comparisons cannot show the rate itself: there it holds unless it shows more false
/// matches than twice the rate allows (at least one).
fn holds(fmr: f64, false_matches: usize, impostors: usize) -> bool {
    if (impostors as f64) * fmr >= 1.0 {
        (0.5..=2.0).contains(&(false_matches as f64 / impostors as f64 / fmr))
    } else {
        false_matches as f64 <= (2.0 * fmr * impostors as f64).max(1.0)
    }
}

/// The shipped thresholds (`shipped`: one photo against one) raised by each checked set's site
/// calibration ([`sites`]) the way the service raises them: the site's templates, each person a
/// subject, give [`SiteRows::calibrate`] (suspected duplicates left out at the shipped model's
/// [`site::extrapolated_duplicate_threshold`]), and [`SiteCalibration::raise`] the threshold.
pub fn report_with_site_calibration(samples: &[Sample], templates: &[Option<Vec<f32>>], shipped: &Calibration) -> CandidateReport {
    let mut rows = Vec::new();
    let duplicate_threshold = site::extrapolated_duplicate_threshold(|fmr| shipped.operating_point(fmr));
    for ((set, keep), site_persons) in checked_sets().into_iter().zip(sites()) {
        let calibration = site_calibration(&kept(samples, templates, &site_persons), duplicate_threshold);
        let (g, i) = pair_scores(samples, templates, None, &keep);
        for point in calibrated_points(|fmr| shipped.operating_point(fmr)) {
            let threshold = calibration.raise(point, point.threshold).threshold;
            rows.push(observed(set, point.fmr, &g, &i, threshold));
        }
    }
    CandidateReport { scoring: Scoring::CosineWithSiteCalibration, calibration: CalibrationPersons::Disjoint, rows }
}

/// Whether a photo is grey: no pixel's channels differ by more than 3 grey levels (a grey JPEG or
/// PGM decodes to equal channels; a colour photo has many pixels far apart).
pub fn is_grey(rgb: &image::RgbImage) -> bool {
    rgb.pixels().all(|p| {
        let [r, g, b] = p.0;
        r.abs_diff(g) <= 3 && g.abs_diff(b) <= 3
    })
}

/// The raw cosine with one threshold table per probe domain (grey or colour photo), each
/// calibrated on the calibration persons' pairs whose probe (the later photo of the pair) is of
/// that domain; checked the same way.
pub fn report_by_probe_domain(
    samples: &[Sample],
    templates: &[Option<Vec<f32>>],
    grey: &[bool],
    calibration: CalibrationPersons,
) -> Vec<Observed> {
    let pairs = |keep: &dyn Fn(&Sample) -> bool, domain: bool| -> (Vec<f32>, Vec<f32>) {
        let items = kept(samples, templates, keep);
        let (mut g, mut imp) = (Vec::new(), Vec::new());
        for a in 0..items.len() {
            for b in a + 1..items.len() {
                if grey[items[b].0] != domain {
                    continue;
                }
                let s = dot(items[a].2, items[b].2);
                if items[a].1 == items[b].1 { g.push(s) } else { imp.push(s) }
            }
        }
        (g, imp)
    };
    let table = |domain: bool| {
        let (g, i) = pairs(&|s| calibration.takes(s), domain);
        Calibration::from_scores(&g, &i, &CALIBRATED_FMRS, "calibration persons")
    };
    let tables = [table(false), table(true)];
    let mut rows = Vec::new();
    for (set, keep) in checked_sets() {
        let scored = [pairs(&keep, false), pairs(&keep, true)];
        for &fmr in &CALIBRATED_FMRS {
            let (mut fm, mut imp, mut fnm, mut gen_) = (0, 0, 0, 0);
            for (domain, (g, i)) in scored.iter().enumerate() {
                let t = tables[domain].operating_point(fmr).threshold;
                fm += i.iter().filter(|&&s| s >= t).count();
                imp += i.len();
                fnm += g.iter().filter(|&&s| s < t).count();
                gen_ += g.len();
            }
            rows.push(Observed {
                set,
                stated: fmr,
                observed: fm as f64 / imp.max(1) as f64,
                false_matches: fm,
                impostors: imp,
                fnmr: fnm as f64 / gen_.max(1) as f64,
                holds: holds(fmr, fm, imp),
            });
        }
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_photo_is_grey_when_no_pixel_has_colour() {
        let tinted = image::RgbImage::from_fn(8, 8, |x, y| image::Rgb([(x * 30) as u8, (x * 30) as u8 + 2, (x * 30 + y) as u8]));
        assert!(!is_grey(&tinted), "blue 5 levels from green at the bottom row");
        let plain = image::RgbImage::from_fn(8, 8, |x, _| image::Rgb([(x * 30) as u8; 3]));
        assert!(is_grey(&plain));
        let mut coloured = plain.clone();
        coloured.put_pixel(3, 3, image::Rgb([200, 90, 90]));
        assert!(!is_grey(&coloured), "one coloured pixel makes a colour photo");
    }
}
