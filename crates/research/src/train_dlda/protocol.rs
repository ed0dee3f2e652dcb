//! Scoring protocols: all pairs, several templates per person, the service's enrolment sets.

use super::*;
use facegate_core::imaging::GrayF32;
use facegate_core::template::Template;
use facegate_vision::recognize::Combine;
use facegate_vision::recognize::normalize;
use facegate_vision::recognize::{ClassicalRecognizer, Views};

/// Template of an aligned face under a model (photometric normalisation, features, projection; the
/// second path's crop too for a fused model: `RecognizeError::Views` when it is missing).
pub fn template_of(
    recognizer: &ClassicalRecognizer,
    aligned: &AlignedFace,
) -> Result<Template, facegate_vision::recognize::RecognizeError> {
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
pub fn pair_scores(recognizer: &ClassicalRecognizer, templates: &[(String, Template)]) -> (Vec<f32>, Vec<f32>) {
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

/// Genuine and impostor scores of each template against every person's other templates, combined.
pub fn combined_scores(recognizer: &ClassicalRecognizer, templates: &[(String, Template)], combine: Combine) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let labels: Vec<&str> = templates.iter().map(|(l, _)| l.as_str()).collect();
    let by_person = crate::eval::protocol::photos_by_person(&labels);
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

/// Genuine and impostor scores of the service's protocol with `k` photos enrolled per person
/// ([`crate::eval::protocol::enrolment_scores_by`]), scored as the recognizer scores.
pub fn enrollment_scores(
    recognizer: &ClassicalRecognizer,
    templates: &[(String, Template)],
    k: usize,
    combine: Combine,
) -> (Vec<f32>, Vec<f32>) {
    let stats: Vec<_> = templates.iter().map(|(_, t)| recognizer.cohort_stats(t)).collect();
    let labels: Vec<&str> = templates.iter().map(|(l, _)| l.as_str()).collect();
    crate::eval::protocol::enrollment_scores_by(&labels, k, combine, &|p, e| {
        recognizer.pair_score(&templates[p].1, stats[p], &templates[e].1, stats[e])
    })
}
