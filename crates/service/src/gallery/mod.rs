//! `/identify` over an in-memory gallery: the current model version's templates in one contiguous
//! f32 matrix, searched with dot products the compiler vectorises, instead of reading and
//! decoding every template from the store per request.
//!
//! [`Gallery`] is the data and the search; [`LiveGallery`] keeps it in step with the [`Store`]:
//! loaded once, then every enrolment and deletion goes through it, store first, gallery second,
//! one at a time and to the end even when the request that asked is cancelled, so the gallery
//! always holds what this process has committed. Where other processes write to the same database
//! (PostgreSQL, several replicas), the store has a change feed ([`Store::watch`]): a background
//! task re-reads each subject another process (or this one) changed, or everything after a lost
//! connection, and records the highest store version applied; an identification first waits until
//! the gallery has applied the version the store had when the request came in
//! ([`LiveGallery::change_version`], [`LiveGallery::wait_until_applied`]).
//!
//! Memory: per template, its vector (4 bytes × dimension), its inverse norm and its subject slot
//! (4 + 4 bytes); per subject, its id and row list (docs/service.md has the measured figure).

mod live;

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use crate::{Candidate, Decision, Matcher};
use facegate_core::vector::dot;
use facegate_vision::recognize::Template;

pub use live::LiveGallery;

/// Why the gallery cannot answer: some stored templates of the current model could not be read
/// (they failed authentication, or their data key cannot be opened). Leaving their subjects out
/// could turn a true match into "no match", so nothing is answered until they are erased.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{count} subject(s) have templates that cannot be read (first: {first}); identification is refused until they are erased")]
pub struct UnreadableTemplates {
    pub count: usize,
    pub first: String,
}

/// One subject's place in the gallery: its id and its rows of the matrix.
#[derive(Debug)]
struct Slot {
    id: Arc<str>,
    rows: Vec<u32>,
}

/// The templates of one model version, as a matrix of rows (one per template) with their subjects.
#[derive(Debug)]
pub struct Gallery {
    model_version: String,
    /// Values per template (0 until the first template).
    dimension: usize,
    /// Row-major, `rows × dimension`.
    vectors: Vec<f32>,
    /// 1 / ‖row‖, or 0 for a zero row (whose cosine is 0, as [`Template::cosine`] has it).
    inv_norms: Vec<f32>,
    /// The slot of each row's subject.
    owners: Vec<u32>,
    slots: Vec<Slot>,
    slot_of: HashMap<Arc<str>, u32>,
    /// Subjects whose templates cannot be read, with why.
    unreadable: BTreeMap<String, String>,
}

impl Gallery {
    pub fn new(model_version: &str) -> Gallery {
        Gallery {
            model_version: model_version.to_string(),
            dimension: 0,
            vectors: Vec::new(),
            inv_norms: Vec::new(),
            owners: Vec::new(),
            slots: Vec::new(),
            slot_of: HashMap::new(),
            unreadable: BTreeMap::new(),
        }
    }

    /// Subjects with at least one template.
    pub fn subjects(&self) -> usize {
        self.slots.len()
    }

    /// Templates held.
    pub fn templates(&self) -> usize {
        self.owners.len()
    }

    /// Add `subject`'s templates of this gallery's model version (others are ignored). A template
    /// of another dimension than the gallery's makes the subject unreadable: it is not comparable.
    pub fn add(&mut self, subject: &str, templates: &[Template]) {
        let mut current = templates.iter().filter(|t| t.model_version == self.model_version).peekable();
        if current.peek().is_none() {
            return;
        }
        let slot = match self.slot_of.get(subject) {
            Some(&slot) => slot,
            None => {
                let id: Arc<str> = Arc::from(subject);
                self.slots.push(Slot { id: id.clone(), rows: Vec::new() });
                self.slot_of.insert(id, (self.slots.len() - 1) as u32);
                (self.slots.len() - 1) as u32
            }
        };
        for template in current {
            if self.dimension == 0 {
                self.dimension = template.vector.len();
            }
            if template.vector.len() != self.dimension || template.vector.is_empty() {
                let message = format!("a template of {} values in a gallery of {}", template.vector.len(), self.dimension);
                self.unreadable.insert(subject.to_string(), message);
                continue;
            }
            let row = self.owners.len() as u32;
            self.vectors.extend_from_slice(&template.vector);
            let norm = template.vector.iter().map(|v| v * v).sum::<f32>().sqrt();
            self.inv_norms.push(if norm > 0.0 { 1.0 / norm } else { 0.0 });
            self.owners.push(slot);
            self.slots[slot as usize].rows.push(row);
        }
    }

    /// Note that `subject`'s templates cannot be read (see [`UnreadableTemplates`]).
    pub fn mark_unreadable(&mut self, subject: &str, why: String) {
        self.unreadable.insert(subject.to_string(), why);
    }

    /// Remove `subject` and all its templates. Rows and slots are filled from the end, so the
    /// matrix stays contiguous.
    pub fn remove(&mut self, subject: &str) {
        self.unreadable.remove(subject);
        let Some(slot) = self.slot_of.remove(subject) else { return };
        let mut rows = std::mem::take(&mut self.slots[slot as usize].rows);
        // Highest first, so that a row moved into a hole is never one still to be removed.
        rows.sort_unstable_by(|a, b| b.cmp(a));
        for row in rows {
            self.remove_row(row as usize);
        }
        let last = self.slots.len() - 1;
        self.slots.swap_remove(slot as usize);
        if (slot as usize) < last {
            let moved = &self.slots[slot as usize];
            for &row in &moved.rows {
                self.owners[row as usize] = slot;
            }
            self.slot_of.insert(moved.id.clone(), slot);
        }
        if self.owners.is_empty() {
            self.dimension = 0;
        }
    }

    fn remove_row(&mut self, row: usize) {
        let last = self.owners.len() - 1;
        let d = self.dimension;
        if row < last {
            self.vectors.copy_within(last * d..(last + 1) * d, row * d);
            let owner = self.owners[last];
            let rows = &mut self.slots[owner as usize].rows;
            let at = rows.iter().position(|&r| r as usize == last).expect("a row is listed by its subject");
            rows[at] = row as u32;
        }
        self.vectors.truncate(last * d);
        self.inv_norms.swap_remove(row);
        self.owners.swap_remove(row);
    }

    fn row(&self, row: usize) -> &[f32] {
        &self.vectors[row * self.dimension..(row + 1) * self.dimension]
    }

    /// The best `k` subjects for `probe`, best first (ties by subject id), each decided at the
    /// threshold for its number of templates: what [`super::identify`] gives for the same
    /// templates. For a matcher whose score is the best cosine ([`Matcher::max_cosine_scoring`]),
    /// scores come from the matrix; for any other, from its own `score` over each subject's
    /// templates. Also returns the number of subjects searched.
    pub fn search(
        &self,
        matcher: &dyn Matcher,
        probe: &Template,
        fmr: f64,
        k: usize,
    ) -> Result<(Vec<Candidate>, usize), UnreadableTemplates> {
        if let Some((first, _)) = self.unreadable.iter().next() {
            return Err(UnreadableTemplates { count: self.unreadable.len(), first: first.clone() });
        }
        let scores = if matcher.max_cosine_scoring() && probe.vector.len() == self.dimension {
            self.best_cosines(&probe.vector)
        } else {
            self.slots
                .iter()
                .map(|slot| {
                    let templates: Vec<Template> = slot
                        .rows
                        .iter()
                        .map(|&r| Template { model_version: self.model_version.clone(), vector: self.row(r as usize).to_vec() })
                        .collect();
                    matcher.score(probe, &templates)
                })
                .collect()
        };
        let mut order: Vec<u32> = (0..self.slots.len() as u32).collect();
        let rank = |a: &u32, b: &u32| {
            scores[*b as usize].total_cmp(&scores[*a as usize]).then_with(|| self.slots[*a as usize].id.cmp(&self.slots[*b as usize].id))
        };
        if k < order.len() {
            order.select_nth_unstable_by(k, rank);
            order.truncate(k);
        }
        order.sort_unstable_by(rank);
        let candidates = order
            .into_iter()
            .map(|s| {
                let (score, templates) = (scores[s as usize], self.slots[s as usize].rows.len());
                let decision = Decision::at(matcher, score, templates, fmr);
                Candidate { subject: self.slots[s as usize].id.to_string(), decision }
            })
            .collect();
        Ok((candidates, self.slots.len()))
    }

    /// Each subject's best cosine with `probe`: one pass over the matrix.
    fn best_cosines(&self, probe: &[f32]) -> Vec<f32> {
        let mut best = vec![f32::NEG_INFINITY; self.slots.len()];
        let probe_norm = probe.iter().map(|v| v * v).sum::<f32>().sqrt();
        let inv_probe = if probe_norm > 0.0 { 1.0 / probe_norm } else { 0.0 };
        if self.dimension == 0 {
            return best;
        }
        for ((row, &inv), &owner) in self.vectors.chunks_exact(self.dimension).zip(&self.inv_norms).zip(&self.owners) {
            let cosine = dot(row, probe) * inv * inv_probe;
            let b = &mut best[owner as usize];
            *b = b.max(cosine);
        }
        best
    }
}

/// The exact reference for [`Gallery::search`]: every subject scored by [`Matcher::score`] on its
/// own, sorted, the best `k` decided at the threshold for their number of templates. The gallery
/// must agree with it (tests) and is measured against it (`cargo bench --bench gallery`).
pub fn score_each_subject(
    matcher: &dyn Matcher,
    probe: &Template,
    gallery: Vec<(String, Vec<Template>)>,
    fmr: f64,
    k: usize,
) -> Vec<Candidate> {
    let mut scored: Vec<(String, f32, usize)> =
        gallery.into_iter().map(|(subject, templates)| (subject, matcher.score(probe, &templates), templates.len())).collect();
    scored.sort_by(|a, b| b.1.total_cmp(&a.1));
    scored.truncate(k);
    scored
        .into_iter()
        .map(|(subject, score, templates)| Candidate { subject, decision: Decision::at(matcher, score, templates, fmr) })
        .collect()
}
