//! Scoring protocols: all pairs, several templates per person, the service's enrolment sets.

use std::collections::BTreeMap;

use super::*;
use crate::core::imaging::GrayF32;
use crate::recognize::normalize;
use crate::recognize::template::{Combine, Template};
use crate::recognize::{Recognizer, Views};

/// Template of an aligned face under a model (photometric normalisation, features, projection; the
/// second path's crop too for a fused model: `RecognizeError::Views` when it is missing).
pub fn template_of(recognizer: &Recognizer, aligned: &AlignedFace) -> Result<Template, crate::recognize::RecognizeError> {
    let params = &recognizer.model().normalize;
    let relit = |c: &GrayF32| {
        let mut crop = c.clone();
        normalize::photometric(&mut crop, params.photometric, &params.mask());
        crop
    };
    let primary = relit(&aligned.crop);
    let secondary = aligned.secondary_crop.as_ref().filter(|_| recognizer.model().secondary.is_some()).map(relit);
    let views = match &secondary {
        Some(secondary) => Views::Fused { primary: &primary, secondary },
        None => Views::Single(&primary),
    };
    recognizer.template(views)
}

/// Genuine and impostor scores of all pairs of templates (one template each), scored as the
/// recognizer scores (cosines, S-normalised when the model has a cohort).
pub fn pair_scores(recognizer: &Recognizer, templates: &[(String, Template)]) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for i in 0..templates.len() {
        for j in i + 1..templates.len() {
            let s = recognizer.pair_score(&templates[i].1, stats[i], &templates[j].1, stats[j]);
            if templates[i].0 == templates[j].0 { genuine.push(s) } else { impostor.push(s) }
        }
    }
    (genuine, impostor)
}

/// The indices of each person's templates, in listing order.
fn photos_by_person(templates: &[(String, Template)]) -> BTreeMap<&str, Vec<usize>> {
    let mut by_person: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, (label, _)) in templates.iter().enumerate() {
        by_person.entry(label).or_default().push(i);
    }
    by_person
}

/// Genuine and impostor scores of each template against every person's other templates, combined.
pub fn combined_scores(recognizer: &Recognizer, templates: &[(String, Template)], combine: Combine) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let by_person = photos_by_person(templates);
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for (p, (label, probe)) in templates.iter().enumerate() {
        for (person, idx) in &by_person {
            let Some(s) =
                combine.apply(idx.iter().filter(|&&i| i != p).map(|&i| recognizer.pair_score(probe, stats[p], &templates[i].1, stats[i])))
            else {
                continue;
            };
            if *person == label.as_str() { genuine.push(s) } else { impostor.push(s) }
        }
    }
    (genuine, impostor)
}

/// Genuine and impostor scores of the service's protocol with `k` photos enrolled per person:
/// each person's photos (in listing order) give one enrolment set per rotation (photos r … r+k−1,
/// cyclically); the person's other photos are its genuine probes, every other person's photos its
/// impostor probes, each scored against the set combined by `combine`. `k` = 1 gives each all-pairs
/// score twice. Persons with no more than `k` photos are left out.
pub fn enrolment_scores(recognizer: &Recognizer, templates: &[(String, Template)], k: usize, combine: Combine) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let by_person = photos_by_person(templates);
    let k = k.max(1);
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for (person, photos) in by_person.iter().filter(|(_, photos)| photos.len() > k) {
        for r in 0..photos.len() {
            let enrolled: Vec<usize> = (0..k).map(|j| photos[(r + j) % photos.len()]).collect();
            for (p, (label, probe)) in templates.iter().enumerate().filter(|(p, _)| !enrolled.contains(p)) {
                let scores = enrolled.iter().map(|&e| recognizer.pair_score(probe, stats[p], &templates[e].1, stats[e]));
                let s = combine.apply(scores).expect("an enrolment set is never empty");
                if label.as_str() == *person { genuine.push(s) } else { impostor.push(s) }
            }
        }
    }
    (genuine, impostor)
}
