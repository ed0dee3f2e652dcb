//! The one-capture, one-person check against a stranger's photo in one step, at the scale its
//! false match rate needs. Each comparison is held at [`rule::CAPTURE_FMR`]; a stranger's frame
//! must pass several of them at once (the probe, and every other step's frames), and this counts
//! how often that happens on LFW's test persons, whom no threshold was calibrated on.
//!
//! A capture is a person's photo as the probe and two more of their photos as two steps (the
//! fewest steps a challenge has is three); it counts only when the person's own frames pass the
//! check, so a refusal is the stranger's doing. Every other person's photo then answers the third
//! step, judged by the service's rule ([`rule::one_person`]).

use std::collections::BTreeMap;

use serde::Serialize;

use facegate_core::template::Template;
use facegate_service::challenge as rule;
use facegate_service::{Matcher, decide};

/// What the stranger-in-one-step check let through.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct StrangerSteps {
    /// Persons with three photos or more whose captures were made.
    pub persons: usize,
    /// Captures (probe and two steps of one person) whose own frames pass the check.
    pub captures: usize,
    /// Captures × every other person's photo in the third step.
    pub attempts: usize,
    /// Attempts whose stranger matched the probe alone at `CAPTURE_FMR`.
    pub matched_probe: usize,
    /// Attempts the one-person check let through (the probe and both other steps matched).
    pub passed: usize,
    /// Those attempts: the capture's probe photo and the stranger's photo.
    pub passed_pairs: Vec<(String, String)>,
}

/// Every capture of `photos` (person, photo name, template) answered by every other person's
/// photo in one step, judged by [`rule::one_person`] under `matcher`.
pub fn stranger_steps(matcher: &dyn Matcher, photos: &[(String, String, Template)]) -> StrangerSteps {
    let mut by_person: BTreeMap<&str, Vec<(&str, &Template)>> = BTreeMap::new();
    for (person, name, template) in photos {
        by_person.entry(person.as_str()).or_default().push((name, template));
    }
    let mut out = StrangerSteps::default();
    for (person, own) in by_person.iter().filter(|(_, t)| t.len() >= 3) {
        out.persons += 1;
        let strangers: Vec<(&str, &Template)> = photos.iter().filter(|(p, ..)| p != person).map(|(_, n, t)| (n.as_str(), t)).collect();
        for i in 0..own.len() {
            let (probe_name, probe) = own[i];
            let steps = [own[(i + 1) % own.len()].1, own[(i + 2) % own.len()].1];
            if rule::one_person(matcher, probe, &steps, &[vec![0], vec![1]]).is_some() {
                continue;
            }
            out.captures += 1;
            for &(stranger_name, stranger) in &strangers {
                out.attempts += 1;
                // The rule compares the stranger with the probe among the rest: one that misses
                // the probe is refused, so the full check is only run on those that match it.
                if !decide(matcher, stranger, std::slice::from_ref(probe), rule::CAPTURE_FMR).is_match {
                    continue;
                }
                out.matched_probe += 1;
                let frames = [steps[0], steps[1], stranger];
                if rule::one_person(matcher, probe, &frames, &[vec![0], vec![1], vec![2]]).is_none() {
                    out.passed += 1;
                    out.passed_pairs.push((probe_name.to_string(), stranger_name.to_string()));
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use facegate_core::template::OperatingPoint;

    /// Cosine of unit vectors, one threshold whatever the FMR.
    struct Cosine(f32);

    impl Matcher for Cosine {
        fn model_version(&self) -> &str {
            "test"
        }
        fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
            enrolled.iter().map(|t| t.vector.iter().zip(&probe.vector).map(|(a, b)| a * b).sum::<f32>()).fold(f32::MIN, f32::max)
        }
        fn operating_point(&self, fmr: f64, _enrolled: usize) -> OperatingPoint {
            OperatingPoint { fmr, threshold: self.0 }
        }
    }

    fn unit(angle: f32) -> Template {
        Template::new("test", vec![angle.cos(), angle.sin()])
    }

    #[test]
    fn a_stranger_passes_only_when_near_the_probe_and_both_steps() {
        // Person a's photos lie at 0, 0.1 and 0.2 rad, and cos ≥ 0.98 is within 0.2 rad: b's
        // photo, at a's middle one, matches all three; c's matches only a's photo at 0.
        let photo = |person: &str, angle: f32| (person.to_string(), format!("{person}{angle}"), unit(angle));
        let photos = vec![photo("a", 0.0), photo("a", 0.1), photo("a", 0.2), photo("b", 0.1), photo("c", -0.19)];
        let steps = stranger_steps(&Cosine(0.98), &photos);
        assert_eq!((steps.persons, steps.captures, steps.attempts), (1, 3, 6));
        // b matches every capture of a (all within 0.2 rad of it); c only the probe at 0.0,
        // never the step at 0.2 (0.39 rad away).
        assert_eq!(steps.passed, 3);
        assert_eq!(steps.passed_pairs[0], ("a0".to_string(), "b0.1".to_string()));
        assert_eq!(steps.matched_probe, 4);
        // A person whose own steps do not match makes no capture.
        let apart = vec![photo("a", 0.0), photo("a", 1.0), photo("a", 2.0)];
        assert_eq!(stranger_steps(&Cosine(0.98), &apart).captures, 0);
    }
}
