//! Verification across head pose (UMIST: each person turns from full profile, photo 01, to near
//! frontal, photo 19). Every photo goes through the service's one pipeline; every pair of photos is
//! scored the way the service would score it, with the more frontal photo of the pair as the
//! enrolled one and the other as the probe (people enrol facing the camera and verify at any
//! angle). A photo whose face is not found scores below every threshold, so a miss counts as a
//! false non-match and never as a false match: the rates are over every pair, not only the scored
//! ones.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use facegate_core::imaging;
use facegate_core::template::Template;
use facegate_vision::pipeline::Pipeline;

use crate::Progress;
use crate::measures::{eer, fnmr_at_fmr};

/// The score of a pair with a photo whose face was not found: below every real score.
pub const MISSED_SCORE: f32 = -1.0e6;

/// The UMIST photos are numbered 01 (full profile) to 19 (near frontal).
pub const UMIST_PHOTOS: u32 = 19;

/// One UMIST photo: `<dir>/sNN/KK.pgm`.
#[derive(Debug, Clone)]
pub struct PosePhoto {
    pub person: String,
    /// 1 (full profile) … 19 (near frontal).
    pub index: u32,
    pub path: PathBuf,
}

/// The UMIST photos under `dir` (one folder per person, photos `01.pgm` … `19.pgm`), by person
/// then photo number.
pub fn list_umist(dir: &Path) -> anyhow::Result<Vec<PosePhoto>> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?.flatten() {
        if !entry.path().is_dir() {
            continue;
        }
        let person = entry.file_name().to_string_lossy().to_string();
        for photo in std::fs::read_dir(entry.path())?.flatten() {
            let path = photo.path();
            let index = path.file_stem().and_then(|s| s.to_str()).and_then(|s| s.parse::<u32>().ok());
            if let Some(index) = index.filter(|i| (1..=UMIST_PHOTOS).contains(i)) {
                out.push(PosePhoto { person: person.clone(), index, path });
            }
        }
    }
    out.sort_by(|a, b| (&a.person, a.index).cmp(&(&b.person, b.index)));
    anyhow::ensure!(!out.is_empty(), "no UMIST photos (sNN/KK.pgm) under {}", dir.display());
    Ok(out)
}

/// What the pipeline made of one photo: nothing (no face), or the photo's own template, the
/// fitted yaw, and the synthetic templates its enrolment would add.
#[derive(Debug, Clone, Default)]
pub struct PoseReading {
    pub template: Option<Template>,
    /// Degrees, from the 3DMM fit; `None` without a face or a fit.
    pub yaw: Option<f32>,
    /// Templates of the fitted head rendered at other yaws, with the yaw (empty unless asked for).
    pub synthetic: Vec<(f32, Template)>,
    /// The template of the 3DMM frontal rendering (unless not asked for).
    pub frontal: Option<Template>,
}

/// Reads every photo through `pipeline` on `threads` threads.
pub fn read_photos(
    pipeline: &Pipeline,
    photos: &[PosePhoto],
    synthetic_yaws: &[f32],
    frontal: bool,
    threads: usize,
    progress: &dyn Progress,
) -> Vec<PoseReading> {
    crate::cache::map_samples(photos, threads, "photos", progress, |p| {
        let Ok(photo) = imaging::open(&p.path) else {
            progress.note(&format!("{}: cannot read", p.path.display()));
            return PoseReading::default();
        };
        match pipeline.analyze(&photo) {
            Ok(analysis) => {
                let synthetic = if synthetic_yaws.is_empty() {
                    Vec::new()
                } else {
                    crate::synthetic::synthetic_templates(pipeline, &photo, &analysis, synthetic_yaws)
                        .into_iter()
                        .map(|s| (s.yaw, s.template))
                        .collect()
                };
                let frontal = if frontal { crate::synthetic::frontal_template(pipeline, &photo, &analysis) } else { None };
                PoseReading { template: Some(analysis.template), yaw: analysis.pose.map(|p| p.yaw), synthetic, frontal }
            }
            Err(_) => PoseReading::default(),
        }
    })
}

/// How enrolled templates are scored against a probe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Strategy {
    /// The enrolled photo's own template only (the service without synthesis).
    Own,
    /// The enrolled photo's template and its synthetic views: the best of them.
    WithSynthetic,
    /// The enrolled photo's template and its one synthetic view nearest the probe's fitted yaw
    /// (the enrolled head rendered at the probe's pose): the better of the two.
    AtProbePose,
    /// Each photo's template made from its 3DMM frontal rendering when its fitted |yaw| is at
    /// least this many degrees, from the photo itself otherwise.
    FrontalBeyond(f32),
}

impl Strategy {
    /// The report's name of the strategy.
    pub fn name(&self) -> String {
        match self {
            Strategy::Own => "own".into(),
            Strategy::WithSynthetic => "synthetic".into(),
            Strategy::AtProbePose => "at-probe-pose".into(),
            Strategy::FrontalBeyond(yaw) => format!("frontal-beyond-{yaw}"),
        }
    }
}

/// One band of probe photos and its rates.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BandResult {
    /// Photo numbers of the band, e.g. `12–19`.
    pub band: String,
    pub genuine: usize,
    pub impostor: usize,
    pub eer: f64,
    pub fnmr_at_fmr_1e3: f64,
    /// At the service's own threshold for FMR 1e-3 (one photo enrolled).
    pub fnmr_at_service_threshold: f64,
    pub fmr_at_service_threshold: f64,
}

/// The report of one strategy.
#[derive(Debug, Clone, serde::Serialize)]
pub struct PoseReport {
    pub strategy: String,
    /// Faces found per photo number (index 0 = photo 01): (found, photos).
    pub found_by_photo: Vec<(usize, usize)>,
    /// Median fitted |yaw| per photo number, degrees.
    pub median_yaw_by_photo: Vec<Option<f32>>,
    pub bands: Vec<BandResult>,
    /// Per probe photo number (index 0 = photo 01): the share of its genuine pairs against an
    /// enrolled photo in 12–19 that match at the service's threshold.
    pub match_rate_by_photo: Vec<f64>,
}

/// The bands reported: every pair, then pairs whose both photos lie in each range of numbers.
pub const BANDS: [(&str, u32, u32); 5] =
    [("01–19", 1, 19), ("12–19", 12, 19), ("06–19", 6, 19), ("01–05 × 12–19", 1, 5), ("01–02 × 12–19", 1, 2)];

/// Pair scores, enrolled = the higher-numbered (more frontal) photo of each pair.
fn pair_score(
    readings: &[PoseReading],
    enrolled: usize,
    probe: usize,
    strategy: Strategy,
    score: &dyn Fn(&Template, &[Template]) -> f32,
) -> f32 {
    let (Some(e), Some(p)) = (&readings[enrolled].template, &readings[probe].template) else {
        return MISSED_SCORE;
    };
    let own = || score(p, std::slice::from_ref(e));
    match strategy {
        Strategy::Own => own(),
        Strategy::WithSynthetic => {
            readings[enrolled].synthetic.iter().map(|(_, s)| score(p, std::slice::from_ref(s))).fold(own(), f32::max)
        }
        Strategy::AtProbePose => {
            let at_pose = readings[probe]
                .yaw
                .and_then(|yaw| readings[enrolled].synthetic.iter().min_by(|a, b| (a.0 - yaw).abs().total_cmp(&(b.0 - yaw).abs())));
            at_pose.map_or_else(own, |(_, s)| own().max(score(p, std::slice::from_ref(s))))
        }
        Strategy::FrontalBeyond(limit) => {
            let template = |r: &PoseReading, own: &Template| {
                r.frontal.as_ref().filter(|_| r.yaw.is_some_and(|y| y.abs() >= limit)).unwrap_or(own).clone()
            };
            score(&template(&readings[probe], p), &[template(&readings[enrolled], e)])
        }
    }
}

/// Whether the pair (enrolled photo number, probe photo number) belongs to band `(lo, hi)`: for the
/// cross bands (`lo` < 12 and `hi` < 12), the probe in `lo..=hi` against an enrolled photo in 12–19.
fn in_band(band: (u32, u32), enrolled: u32, probe: u32) -> bool {
    let (lo, hi) = band;
    if hi < 12 {
        (lo..=hi).contains(&probe) && (12..=19).contains(&enrolled)
    } else {
        (lo..=hi).contains(&probe) && (lo..=hi).contains(&enrolled)
    }
}

/// Every band's rates for one strategy; `service_threshold` is the loaded model's FMR 1e-3
/// threshold for one enrolled photo.
pub fn report(
    photos: &[PosePhoto],
    readings: &[PoseReading],
    strategy: Strategy,
    service_threshold: f32,
    score: &(dyn Fn(&Template, &[Template]) -> f32 + Sync),
) -> PoseReport {
    let mut pairs: Vec<(usize, usize, bool, f32)> = Vec::new();
    for i in 0..photos.len() {
        for j in i + 1..photos.len() {
            // The more frontal photo (higher number) is the enrolled one.
            let (e, p) = if photos[j].index > photos[i].index { (j, i) } else { (i, j) };
            pairs.push((e, p, photos[e].person == photos[p].person, pair_score(readings, e, p, strategy, score)));
        }
    }
    let bands = BANDS
        .iter()
        .map(|&(name, lo, hi)| {
            let (mut g, mut imp) = (Vec::new(), Vec::new());
            for &(e, p, same, s) in &pairs {
                if in_band((lo, hi), photos[e].index, photos[p].index) {
                    if same { g.push(s) } else { imp.push(s) }
                }
            }
            let rate =
                |v: &[f32], above: bool| v.iter().filter(|&&s| (s >= service_threshold) == above).count() as f64 / v.len().max(1) as f64;
            BandResult {
                band: name.to_string(),
                genuine: g.len(),
                impostor: imp.len(),
                eer: eer(&g, &imp),
                fnmr_at_fmr_1e3: fnmr_at_fmr(&g, &imp, 1e-3).0,
                fnmr_at_service_threshold: rate(&g, false),
                fmr_at_service_threshold: rate(&imp, true),
            }
        })
        .collect();
    let mut matched = vec![(0usize, 0usize); UMIST_PHOTOS as usize];
    for &(e, p, same, s) in &pairs {
        if same && photos[e].index >= 12 {
            let slot = &mut matched[photos[p].index as usize - 1];
            slot.0 += (s >= service_threshold) as usize;
            slot.1 += 1;
        }
    }
    let match_rate_by_photo = matched.iter().map(|&(m, n)| m as f64 / n.max(1) as f64).collect();
    let mut found_by_photo = vec![(0, 0); UMIST_PHOTOS as usize];
    let mut yaws: BTreeMap<u32, Vec<f32>> = BTreeMap::new();
    for (p, r) in photos.iter().zip(readings) {
        let slot = &mut found_by_photo[p.index as usize - 1];
        slot.1 += 1;
        slot.0 += r.template.is_some() as usize;
        if let Some(y) = r.yaw {
            yaws.entry(p.index).or_default().push(y.abs());
        }
    }
    let median_yaw_by_photo = (1..=UMIST_PHOTOS)
        .map(|i| {
            let mut v = yaws.get(&i)?.clone();
            v.sort_by(f32::total_cmp);
            Some(v[v.len() / 2])
        })
        .collect();
    PoseReport { strategy: strategy.name(), found_by_photo, median_yaw_by_photo, bands, match_rate_by_photo }
}

/// One pose band's observed rates on persons left out, at a threshold for FMR 1e-3 calibrated on
/// the other persons' impostor pairs: of that band alone, and of every pair together.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BandThresholdResult {
    pub band: String,
    pub genuine: usize,
    pub impostor: usize,
    pub fmr_band_threshold: f64,
    pub fnmr_band_threshold: f64,
    pub fmr_one_threshold: f64,
    pub fnmr_one_threshold: f64,
}

/// Thresholds per pose band against one threshold, by person folds (the photos' own templates):
/// fold `k` holds out the persons whose rank is `k` modulo `folds`; its thresholds come from the
/// impostor pairs among the other persons (per band, and over every pair), and are applied to the
/// pairs with a held-out person. Rates pooled over the folds.
pub fn band_thresholds(
    photos: &[PosePhoto],
    readings: &[PoseReading],
    folds: usize,
    score: &(dyn Fn(&Template, &[Template]) -> f32 + Sync),
) -> Vec<BandThresholdResult> {
    let mut persons: Vec<&str> = photos.iter().map(|p| p.person.as_str()).collect();
    persons.sort_unstable();
    persons.dedup();
    let fold_of = |person: &str| persons.iter().position(|&q| q == person).unwrap_or(0) % folds.max(1);
    let mut pairs: Vec<(usize, usize, bool, f32)> = Vec::new();
    for i in 0..photos.len() {
        for j in i + 1..photos.len() {
            let (e, p) = if photos[j].index > photos[i].index { (j, i) } else { (i, j) };
            pairs.push((e, p, photos[e].person == photos[p].person, pair_score(readings, e, p, Strategy::Own, score)));
        }
    }
    let in_any = |&(lo, hi): &(u32, u32), e: usize, p: usize| in_band((lo, hi), photos[e].index, photos[p].index);
    BANDS
        .iter()
        .map(|&(name, lo, hi)| {
            // (genuine, impostor) × (band threshold, one threshold): [accepted, total].
            let mut counts = [[0usize; 2]; 4];
            for k in 0..folds.max(1) {
                let held = |i: usize| fold_of(&photos[i].person) == k;
                let calibration = |band: Option<(u32, u32)>| -> Vec<f32> {
                    let inside = |&&(e, p, same, _): &&(usize, usize, bool, f32)| {
                        !same && !held(e) && !held(p) && band.is_none_or(|b| in_any(&b, e, p))
                    };
                    pairs.iter().filter(inside).map(|x| x.3).collect()
                };
                let band_t = fnmr_at_fmr(&[], &calibration(Some((lo, hi))), 1e-3).1;
                let one_t = fnmr_at_fmr(&[], &calibration(None), 1e-3).1;
                for &(_, _, same, s) in pairs.iter().filter(|&&(e, p, _, _)| (held(e) || held(p)) && in_any(&(lo, hi), e, p)) {
                    let row = if same { 0 } else { 2 };
                    for (slot, t) in [(row, band_t), (row + 1, one_t)] {
                        counts[slot][0] += (s >= t) as usize;
                        counts[slot][1] += 1;
                    }
                }
            }
            let rate = |c: [usize; 2]| c[0] as f64 / c[1].max(1) as f64;
            BandThresholdResult {
                band: name.to_string(),
                genuine: counts[0][1],
                impostor: counts[2][1],
                fmr_band_threshold: rate(counts[2]),
                fnmr_band_threshold: 1.0 - rate(counts[0]),
                fmr_one_threshold: rate(counts[3]),
                fnmr_one_threshold: 1.0 - rate(counts[1]),
            }
        })
        .collect()
}

impl PoseReport {
    /// Faces found over every photo, as a fraction.
    pub fn found_rate(&self) -> f64 {
        let (f, n) = self.found_by_photo.iter().fold((0, 0), |(a, b), &(f, n)| (a + f, b + n));
        f as f64 / n.max(1) as f64
    }

    /// A Markdown table of the bands.
    pub fn markdown(&self) -> String {
        let mut out = format!(
            "strategy `{}`: faces found {:.1}%\n\n| pairs (photo numbers) | genuine | impostor | EER | FNMR @ FMR 1e-3 | FNMR / FMR at the service's 1e-3 threshold |\n|---|---|---|---|---|---|\n",
            self.strategy,
            100.0 * self.found_rate()
        );
        for b in &self.bands {
            out += &format!(
                "| {} | {} | {} | {:.2}% | {:.2}% | {:.2}% / {:.4}% |\n",
                b.band,
                b.genuine,
                b.impostor,
                100.0 * b.eer,
                100.0 * b.fnmr_at_fmr_1e3,
                100.0 * b.fnmr_at_service_threshold,
                100.0 * b.fmr_at_service_threshold
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn photo(person: &str, index: u32) -> PosePhoto {
        PosePhoto { person: person.into(), index, path: PathBuf::new() }
    }

    fn reading(v: [f32; 2]) -> PoseReading {
        PoseReading { template: Some(Template::new("t", v.to_vec())), yaw: Some(0.0), synthetic: Vec::new(), frontal: None }
    }

    fn cosine(p: &Template, e: &[Template]) -> f32 {
        e.iter().map(|t| p.cosine(t)).fold(f32::NEG_INFINITY, f32::max)
    }

    /// A missed photo's pairs stay in the counts and fail every genuine comparison.
    #[test]
    fn a_missed_face_is_a_false_non_match_not_a_dropped_pair() {
        let photos = [photo("a", 19), photo("a", 1), photo("b", 19), photo("b", 1)];
        let readings = [reading([1.0, 0.0]), PoseReading::default(), reading([0.0, 1.0]), reading([0.1, 1.0])];
        let r = report(&photos, &readings, Strategy::Own, 0.5, &cosine);
        let all = &r.bands[0];
        assert_eq!((all.genuine, all.impostor), (2, 4));
        assert_eq!(all.fnmr_at_service_threshold, 0.5, "person a's pair is missed");
        assert_eq!(r.found_by_photo[0], (1, 2));
        assert_eq!(r.found_by_photo[18], (2, 2));
    }

    /// Synthetic views of the enrolled photo can lift a turned probe's genuine score.
    #[test]
    fn synthetic_views_score_by_the_best_template() {
        let photos = [photo("a", 19), photo("a", 2)];
        let mut frontal = reading([1.0, 0.0]);
        frontal.synthetic = vec![(30.0, Template::new("t", vec![0.0, 1.0]))];
        let readings = [frontal, reading([0.0, 1.0])];
        let own = report(&photos, &readings, Strategy::Own, 0.5, &cosine);
        let synth = report(&photos, &readings, Strategy::WithSynthetic, 0.5, &cosine);
        assert_eq!(own.bands[0].fnmr_at_service_threshold, 1.0);
        assert_eq!(synth.bands[0].fnmr_at_service_threshold, 0.0);
    }

    /// The enrolled head rendered at the probe's pose scores by the one render nearest the probe's
    /// yaw, not the best of all; frontal templates replace a photo's own beyond the yaw given.
    #[test]
    fn the_probes_pose_picks_one_render_and_frontalising_follows_the_yaw() {
        let photos = [photo("a", 19), photo("a", 2)];
        let mut enrolled = reading([1.0, 0.0]);
        enrolled.synthetic = vec![(-60.0, Template::new("t", vec![0.0, 1.0])), (60.0, Template::new("t", vec![1.0, 0.0]))];
        let mut probe = reading([0.0, 1.0]);
        probe.yaw = Some(70.0);
        let readings = [enrolled.clone(), probe.clone()];
        assert_eq!(report(&photos, &readings, Strategy::WithSynthetic, 0.5, &cosine).bands[0].fnmr_at_service_threshold, 0.0);
        assert_eq!(report(&photos, &readings, Strategy::AtProbePose, 0.5, &cosine).bands[0].fnmr_at_service_threshold, 1.0);
        probe.yaw = Some(-70.0);
        let readings = [enrolled.clone(), probe.clone()];
        assert_eq!(report(&photos, &readings, Strategy::AtProbePose, 0.5, &cosine).bands[0].fnmr_at_service_threshold, 0.0);
        probe.frontal = Some(Template::new("t", vec![1.0, 0.0]));
        let readings = [enrolled, probe];
        assert_eq!(report(&photos, &readings, Strategy::FrontalBeyond(60.0), 0.5, &cosine).bands[0].fnmr_at_service_threshold, 0.0);
        assert_eq!(report(&photos, &readings, Strategy::FrontalBeyond(80.0), 0.5, &cosine).bands[0].fnmr_at_service_threshold, 1.0);
    }

    /// Thresholds come from the persons outside each fold: an impostor pair among the held-out
    /// persons scoring above every calibration impostor is a false match.
    #[test]
    fn band_thresholds_are_calibrated_on_other_persons() {
        let photos: Vec<PosePhoto> = ["a", "b", "c", "d"].iter().flat_map(|p| [photo(p, 19), photo(p, 12)]).collect();
        let angle = |deg: f32| reading([deg.to_radians().cos(), deg.to_radians().sin()]);
        // Each person's two photos 5° apart, persons 30° apart.
        let readings: Vec<PoseReading> = (0..4).flat_map(|k| [angle(30.0 * k as f32), angle(30.0 * k as f32 + 5.0)]).collect();
        let rows = band_thresholds(&photos, &readings, 2, &cosine);
        let all = &rows[0];
        assert_eq!(all.genuine, 4);
        assert_eq!((all.fnmr_band_threshold, all.fnmr_one_threshold), (0.0, 0.0));
        assert!(all.fmr_band_threshold > 0.0, "impostors 25° apart against a threshold from pairs 55° apart and more");
    }

    #[test]
    fn cross_bands_pair_turned_probes_with_frontal_enrolment() {
        assert!(in_band((1, 5), 15, 3));
        assert!(!in_band((1, 5), 8, 3));
        assert!(!in_band((1, 5), 15, 8));
        assert!(in_band((12, 19), 15, 12));
        assert!(!in_band((12, 19), 15, 11));
    }
}

/// The held-out sets every change of the front end must not make worse: LFW's test persons and
/// IMM's and ORL's held-out persons (`train_deep::list_samples`' split), as [`PosePhoto`]s with
/// photo number 0.
pub fn held_out_sets(shared: &Path) -> anyhow::Result<Vec<(&'static str, Vec<PosePhoto>)>> {
    use crate::dataset::Split;
    use crate::train_deep::{Set, list_samples};
    let samples = list_samples(shared)?;
    let pick = |set: Set| -> Vec<PosePhoto> {
        samples
            .iter()
            .filter(|s| s.set == set && s.split == Split::Test)
            .map(|s| PosePhoto { person: s.label.clone(), index: 0, path: s.image.clone() })
            .collect()
    };
    Ok(vec![("LFW test persons", pick(Set::Lfw)), ("IMM held-out", pick(Set::Imm)), ("ORL held-out", pick(Set::Orl))])
}

/// One held-out set's all-pairs rates (one photo against one).
#[derive(Debug, Clone, serde::Serialize)]
pub struct HeldOutResult {
    pub set: String,
    pub photos: usize,
    pub found: usize,
    pub eer: f64,
    pub fnmr_at_fmr_1e3: f64,
    pub fmr_at_service_threshold: f64,
}

pub fn held_out(
    name: &str,
    photos: &[PosePhoto],
    readings: &[PoseReading],
    service_threshold: f32,
    score: &(dyn Fn(&Template, &[Template]) -> f32 + Sync),
) -> HeldOutResult {
    let labels: Vec<&str> = photos.iter().map(|p| p.person.as_str()).collect();
    let pair = |i: usize, j: usize| match (&readings[i].template, &readings[j].template) {
        (Some(a), Some(b)) => score(a, std::slice::from_ref(b)),
        _ => MISSED_SCORE,
    };
    let (g, i) = crate::eval::protocol::all_pairs_by(&labels, &pair);
    HeldOutResult {
        set: name.to_string(),
        photos: photos.len(),
        found: readings.iter().filter(|r| r.template.is_some()).count(),
        eer: eer(&g, &i),
        fnmr_at_fmr_1e3: fnmr_at_fmr(&g, &i, 1e-3).0,
        fmr_at_service_threshold: i.iter().filter(|&&s| s >= service_threshold).count() as f64 / i.len().max(1) as f64,
    }
}

/// One yaw of [`render_curve`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct RenderPoint {
    /// Degrees of the rendering.
    pub yaw: f32,
    pub renders: usize,
    /// Renderings whose face the pipeline found.
    pub found: usize,
    /// Mean genuine score over the found ones.
    pub mean_genuine: f64,
    /// Share of all renderings that match at the service's threshold (misses do not).
    pub match_rate: f64,
}

/// Genuine scores against yaw on 3DMM renderings: for each person with two photos or more, the
/// first photo is enrolled and the second's fitted, textured head is rendered at each of `yaws`
/// (pitch and roll kept) and verified through the pipeline like any photo.
pub fn render_curve(
    pipeline: &Pipeline,
    photos: &[PosePhoto],
    yaws: &[f32],
    service_threshold: f32,
    threads: usize,
    progress: &dyn Progress,
) -> Vec<RenderPoint> {
    let by_person = crate::eval::protocol::photos_by_person(&photos.iter().map(|p| p.person.as_str()).collect::<Vec<_>>());
    let pairs: Vec<(usize, usize)> = by_person.values().filter(|v| v.len() >= 2).map(|v| (v[0], v[1])).collect();
    let per_pair: Vec<Vec<Option<f32>>> = crate::cache::map_samples(&pairs, threads, "renders", progress, |&(e, p)| {
        let score = || -> Option<Vec<Option<f32>>> {
            let enrolled = pipeline.analyze(&imaging::open(&photos[e].path).ok()?).ok()?.template;
            let photo = imaging::open(&photos[p].path).ok()?;
            let analysis = pipeline.analyze(&photo).ok()?;
            let model = pipeline.face_model.as_ref()?;
            let fit = model.fit(&analysis.landmarks.points, photo.width(), photo.height()).ok()?;
            let poses: Vec<_> = yaws.iter().map(|&yaw| facegate_morph::Pose { yaw, ..fit.pose }).collect();
            let views = crate::synthetic::render_at(model, &photo, &fit, &analysis.landmarks.points, &poses);
            Some(
                views
                    .iter()
                    .map(|(view, _)| {
                        pipeline.analyze(view).ok().map(|a| pipeline.recognizer.score(&a.template, std::slice::from_ref(&enrolled)))
                    })
                    .collect(),
            )
        };
        score().unwrap_or_default()
    });
    yaws.iter()
        .enumerate()
        .map(|(k, &yaw)| {
            let scores: Vec<Option<f32>> = per_pair.iter().filter(|v| v.len() == yaws.len()).map(|v| v[k]).collect();
            let found: Vec<f32> = scores.iter().flatten().copied().collect();
            RenderPoint {
                yaw,
                renders: scores.len(),
                found: found.len(),
                mean_genuine: found.iter().map(|&s| s as f64).sum::<f64>() / found.len().max(1) as f64,
                match_rate: found.iter().filter(|&&s| s >= service_threshold).count() as f64 / scores.len().max(1) as f64,
            }
        })
        .collect()
}
