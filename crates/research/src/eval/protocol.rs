//! The scoring protocols, for any recognizer: a score between two photos (by index) and each
//! photo's person label in, genuine and impostor scores out.

use std::collections::BTreeMap;

use facegate_vision::recognize::Combine;

/// The cosine of two unit templates (their dot product, summed in order): the score every
/// research protocol gives a pair of the deep models' templates.
pub fn unit_cosine(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Genuine and impostor scores of all pairs (one template each).
pub fn all_pairs_by(labels: &[&str], score: &(dyn Fn(usize, usize) -> f32 + Sync)) -> (Vec<f32>, Vec<f32>) {
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for i in 0..labels.len() {
        for j in i + 1..labels.len() {
            let s = score(i, j);
            if labels[i] == labels[j] { genuine.push(s) } else { impostor.push(s) }
        }
    }
    (genuine, impostor)
}

/// The indices of each person's photos, in listing order.
pub fn photos_by_person<'a>(labels: &[&'a str]) -> BTreeMap<&'a str, Vec<usize>> {
    let mut by_person: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, label) in labels.iter().enumerate() {
        by_person.entry(label).or_default().push(i);
    }
    by_person
}

/// Genuine and impostor scores of the service's protocol with `k` photos enrolled per person:
/// each person's photos (in listing order) give one enrolment set per rotation (photos r … r+k−1,
/// cyclically); the person's other photos are its genuine probes, every other person's photos its
/// impostor probes, each scored against the set combined by `combine` (`score(probe, enrolled)`).
/// `k` = 1 gives each all-pairs score twice. Persons with no more than `k` photos are left out as
/// enrolled subjects.
pub fn enrollment_scores_by(
    labels: &[&str],
    k: usize,
    combine: Combine,
    score: &(dyn Fn(usize, usize) -> f32 + Sync),
) -> (Vec<f32>, Vec<f32>) {
    let by_person = photos_by_person(labels);
    let k = k.max(1);
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for (person, photos) in by_person.iter().filter(|(_, photos)| photos.len() > k) {
        for r in 0..photos.len() {
            let enrolled: Vec<usize> = (0..k).map(|j| photos[(r + j) % photos.len()]).collect();
            for (p, label) in labels.iter().enumerate().filter(|(p, _)| !enrolled.contains(p)) {
                let s = combine.apply(enrolled.iter().map(|&e| score(p, e))).expect("an enrolment set is never empty");
                if label == person { genuine.push(s) } else { impostor.push(s) }
            }
        }
    }
    (genuine, impostor)
}
