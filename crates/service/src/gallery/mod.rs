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
//! Memory: per template, its values (exact: 4 bytes × dimension and an inverse norm; quantised:
//! half a byte × dimension and a scale) and its subject slot (4 bytes); per subject, its id and
//! an index entry (docs/gallery.md has the measured figures).

pub mod codes;
mod live;

use std::collections::BTreeMap;
use std::hash::BuildHasher;

use hashbrown::{DefaultHashBuilder, HashTable};

use crate::{Candidate, Decision, Matcher};
use facegate_core::template::Template;
use facegate_core::vector::dot;

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

/// How a gallery holds its templates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    /// As floats: the search scores every subject exactly (any matcher).
    Exact,
    /// In 4 bits per value ([`codes`]): the search shortlists subjects by their approximate best
    /// cosine, to be re-scored exactly from the store ([`LiveGallery::rerank`]). For matchers
    /// whose score is the best cosine; an eighth of the memory and of the bytes scanned.
    Quantised,
}

/// What a search found.
#[derive(Debug, Clone, PartialEq)]
pub enum Found {
    /// The best `k` subjects, scored and decided (an exact gallery).
    Decided(Vec<Candidate>),
    /// Subjects whose exact scores decide the answer, in id order (a quantised gallery): the
    /// best `k + SHORTLIST_MARGIN` by approximate score, or every subject when the approximation
    /// does not apply (a matcher that is not the best cosine, a probe of another dimension).
    Shortlist(Vec<String>),
}

/// Subjects shortlisted beyond the `k` asked for, so that a true top-`k` subject whose
/// approximate score fell a little is still re-scored (docs/gallery.md measures the recall).
pub const SHORTLIST_MARGIN: usize = 32;

/// The templates of one model version with their subjects: per template (row) its values and its
/// subject slot; per subject slot its id. A subject's rows are found by their slot (a scan of the
/// slots on deletion, a few milliseconds at ten million) rather than kept in a list per subject,
/// which would cost more memory than a quantised template.
#[derive(Debug)]
pub struct Gallery {
    model_version: String,
    precision: Precision,
    /// Values per template (0 until the first template).
    dimension: usize,
    /// Exact: row-major, `rows × dimension`.
    vectors: Vec<f32>,
    /// Exact: 1 / ‖row‖, or 0 for a zero row (whose cosine is 0, as [`Template::cosine`] has it).
    inv_norms: Vec<f32>,
    /// Quantised: `rows × codes::code_len(dimension)` bytes.
    codes: Vec<u8>,
    /// Quantised: each row's factor from integer dot product to cosine.
    scales: Vec<f32>,
    /// The slot of each row's subject.
    owners: Vec<u32>,
    /// Each slot's subject id.
    ids: Vec<Box<str>>,
    /// Slots by subject id (hashed by `hasher`).
    slot_of: HashTable<u32>,
    /// foldhash with a per-process seed: several times faster than SipHash on ten million ids.
    hasher: DefaultHashBuilder,
    /// Subjects whose templates cannot be read, with why.
    unreadable: BTreeMap<String, String>,
}

/// Room for the values of `rows` more rows of `dimension` values held at `precision` (none for
/// quantised rows until the dimension is known). A free function so that `Gallery::add` can call
/// it while it borrows the model version.
fn reserve_values(precision: Precision, dimension: usize, rows: usize, vectors: &mut Vec<f32>, codes: &mut Vec<u8>) {
    match precision {
        Precision::Exact => vectors.reserve(rows * dimension),
        Precision::Quantised if dimension > 0 => codes.reserve(rows * codes::code_len(dimension)),
        Precision::Quantised => {}
    }
}

impl Gallery {
    /// An exact gallery of `model_version`'s templates.
    pub fn new(model_version: &str) -> Gallery {
        Gallery::with_precision(model_version, Precision::Exact)
    }

    pub fn with_precision(model_version: &str, precision: Precision) -> Gallery {
        Gallery {
            model_version: model_version.to_string(),
            precision,
            dimension: 0,
            vectors: Vec::new(),
            inv_norms: Vec::new(),
            codes: Vec::new(),
            scales: Vec::new(),
            owners: Vec::new(),
            ids: Vec::new(),
            slot_of: HashTable::new(),
            hasher: DefaultHashBuilder::default(),
            unreadable: BTreeMap::new(),
        }
    }

    /// Room for about `templates` more templates (of as many subjects), reserved at once: the
    /// start-up load adds millions, and growing by doubling copied the arrays and re-hashed every
    /// id at each step. The values' room is reserved with the first template, whose dimension
    /// sets it.
    pub fn reserve(&mut self, templates: usize) {
        self.owners.reserve(templates);
        self.ids.reserve(templates);
        match self.precision {
            Precision::Exact => self.inv_norms.reserve(templates),
            Precision::Quantised => self.scales.reserve(templates),
        }
        let (ids, hasher) = (&self.ids, &self.hasher);
        self.slot_of.reserve(templates, |&s| hasher.hash_one(&*ids[s as usize]));
        let rows = self.owners.capacity() - self.owners.len();
        reserve_values(self.precision, self.dimension, rows, &mut self.vectors, &mut self.codes);
    }

    pub fn model_version(&self) -> &str {
        &self.model_version
    }

    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Subjects with at least one template.
    pub fn subjects(&self) -> usize {
        self.ids.len()
    }

    /// Templates held.
    pub fn templates(&self) -> usize {
        self.owners.len()
    }

    fn find_slot(&self, subject: &str) -> Option<u32> {
        self.find_hashed(self.hasher.hash_one(subject), subject)
    }

    fn find_hashed(&self, hash: u64, subject: &str) -> Option<u32> {
        self.slot_of.find(hash, |&s| &*self.ids[s as usize] == subject).copied()
    }

    /// Add `subject`'s templates of this gallery's model version (others are ignored). A template
    /// of another dimension than the gallery's makes the subject unreadable: it is not comparable.
    pub fn add(&mut self, subject: &str, templates: &[Template]) {
        let mut current = templates.iter().filter(|t| t.model_version == self.model_version).peekable();
        if current.peek().is_none() {
            return;
        }
        // Hashed once for the lookup and the insertion: the start-up load adds millions.
        let hash = self.hasher.hash_one(subject);
        let (slot, new) = match self.find_hashed(hash, subject) {
            Some(slot) => (slot, false),
            None => {
                let slot = self.ids.len() as u32;
                self.ids.push(Box::from(subject));
                let (ids, hasher) = (&self.ids, &self.hasher);
                self.slot_of.insert_unique(hash, slot, |&s| hasher.hash_one(&*ids[s as usize]));
                (slot, true)
            }
        };
        let rows_before = self.owners.len();
        for template in current {
            if self.dimension == 0 {
                self.dimension = template.vector.len();
                let rows = self.owners.capacity() - self.owners.len();
                reserve_values(self.precision, self.dimension, rows, &mut self.vectors, &mut self.codes);
            }
            if template.vector.len() != self.dimension || template.vector.is_empty() {
                let message = format!("a template of {} values in a gallery of {}", template.vector.len(), self.dimension);
                self.unreadable.insert(subject.to_string(), message);
                continue;
            }
            match self.precision {
                Precision::Exact => {
                    self.vectors.extend_from_slice(&template.vector);
                    let norm = template.vector.iter().map(|v| v * v).sum::<f32>().sqrt();
                    self.inv_norms.push(if norm > 0.0 { 1.0 / norm } else { 0.0 });
                }
                Precision::Quantised => self.scales.push(codes::encode(&template.vector, &mut self.codes)),
            }
            self.owners.push(slot);
        }
        if new && self.owners.len() == rows_before {
            // Every template was refused: a new subject holds no row.
            self.remove_slot(slot);
        }
    }

    /// Take in `part`, a gallery of the same model version and precision holding other subjects
    /// (a part of the store read on its own: [`LiveGallery::load`]). Where the two disagree on
    /// the dimension, `part`'s subjects are noted unreadable, as [`Gallery::add`] notes a
    /// template of another dimension.
    pub fn absorb(&mut self, part: Gallery) {
        assert_eq!((&self.model_version, self.precision), (&part.model_version, part.precision), "parts of one gallery");
        self.unreadable.extend(part.unreadable);
        if part.dimension != 0 && self.dimension != 0 && part.dimension != self.dimension {
            for id in part.ids {
                let message = format!("templates of {} values in a gallery of {}", part.dimension, self.dimension);
                self.unreadable.insert(id.into(), message);
            }
            return;
        }
        if self.dimension == 0 {
            self.dimension = part.dimension;
        }
        let offset = self.ids.len() as u32;
        // Exactly: a doubling of ten million codes would be a gigabyte more at the peak.
        self.owners.reserve_exact(part.owners.len());
        self.codes.reserve_exact(part.codes.len());
        self.scales.reserve_exact(part.scales.len());
        self.ids.reserve_exact(part.ids.len());
        self.owners.extend(part.owners.iter().map(|o| o + offset));
        self.vectors.extend_from_slice(&part.vectors);
        self.inv_norms.extend_from_slice(&part.inv_norms);
        self.codes.extend_from_slice(&part.codes);
        self.scales.extend_from_slice(&part.scales);
        self.slot_of.reserve(part.ids.len(), |&s| self.hasher.hash_one(&*self.ids[s as usize]));
        for id in part.ids {
            let slot = self.ids.len() as u32;
            let hash = self.hasher.hash_one(&*id);
            self.ids.push(id);
            let (ids, hasher) = (&self.ids, &self.hasher);
            self.slot_of.insert_unique(hash, slot, |&s| hasher.hash_one(&*ids[s as usize]));
        }
    }

    /// Note that `subject`'s templates cannot be read (see [`UnreadableTemplates`]).
    pub fn mark_unreadable(&mut self, subject: &str, why: String) {
        self.unreadable.insert(subject.to_string(), why);
    }

    /// Remove `subject` and all its templates. The last rows and the last slot fill the holes, so
    /// the arrays stay contiguous.
    pub fn remove(&mut self, subject: &str) {
        self.unreadable.remove(subject);
        if let Some(slot) = self.find_slot(subject) {
            self.remove_slot(slot);
        }
    }

    fn remove_slot(&mut self, slot: u32) {
        // Highest first, so that a row moved into a hole is never one still to be removed.
        let rows: Vec<usize> = (0..self.owners.len()).rev().filter(|&r| self.owners[r] == slot).collect();
        for row in rows {
            self.remove_row(row);
        }
        let hash = self.hasher.hash_one(&*self.ids[slot as usize]);
        self.slot_of.find_entry(hash, |&s| s == slot).expect("a slot is indexed by its id").remove();
        let last = (self.ids.len() - 1) as u32;
        self.ids.swap_remove(slot as usize);
        if slot < last {
            // The last slot moved into the hole: its rows and its index entry follow.
            for owner in self.owners.iter_mut().filter(|o| **o == last) {
                *owner = slot;
            }
            let hash = self.hasher.hash_one(&*self.ids[slot as usize]);
            *self.slot_of.find_mut(hash, |&s| s == last).expect("a slot is indexed by its id") = slot;
        }
        if self.owners.is_empty() {
            self.dimension = 0;
        }
    }

    fn remove_row(&mut self, row: usize) {
        let last = self.owners.len() - 1;
        match self.precision {
            Precision::Exact => {
                let d = self.dimension;
                self.vectors.copy_within(last * d..(last + 1) * d, row * d);
                self.vectors.truncate(last * d);
                self.inv_norms.swap_remove(row);
            }
            Precision::Quantised => {
                let len = codes::code_len(self.dimension);
                self.codes.copy_within(last * len..(last + 1) * len, row * len);
                self.codes.truncate(last * len);
                self.scales.swap_remove(row);
            }
        }
        self.owners.swap_remove(row);
    }

    fn row(&self, row: usize) -> &[f32] {
        &self.vectors[row * self.dimension..(row + 1) * self.dimension]
    }

    /// Each slot's rows, in row order.
    fn rows_by_slot(&self) -> Vec<Vec<u32>> {
        let mut rows = vec![Vec::new(); self.ids.len()];
        for (row, &owner) in self.owners.iter().enumerate() {
            rows[owner as usize].push(row as u32);
        }
        rows
    }

    /// The best `k` subjects for `probe`. An exact gallery decides them (best first, ties by
    /// subject id, each at the threshold for its number of templates): what
    /// [`score_each_subject`] gives for the same templates; for a matcher whose score is the best
    /// cosine ([`Matcher::max_cosine_scoring`]) scores come from the matrix, for any other from
    /// its own `score`. A quantised gallery shortlists them ([`Found::Shortlist`]). Also returns
    /// the number of subjects searched.
    pub fn search(&self, matcher: &dyn Matcher, probe: &Template, fmr: f64, k: usize) -> Result<(Found, usize), UnreadableTemplates> {
        if let Some((first, _)) = self.unreadable.iter().next() {
            return Err(UnreadableTemplates { count: self.unreadable.len(), first: first.clone() });
        }
        let cosine = matcher.max_cosine_scoring() && probe.vector.len() == self.dimension;
        let found = match self.precision {
            Precision::Quantised if cosine => Found::Shortlist(self.shortlist(&probe.vector, k + SHORTLIST_MARGIN)),
            Precision::Quantised => {
                let mut everyone: Vec<String> = self.ids.iter().map(|id| id.to_string()).collect();
                everyone.sort_unstable();
                Found::Shortlist(everyone)
            }
            Precision::Exact => Found::Decided(self.decide_exactly(matcher, probe, fmr, k, cosine)),
        };
        Ok((found, self.ids.len()))
    }

    fn decide_exactly(&self, matcher: &dyn Matcher, probe: &Template, fmr: f64, k: usize, cosine: bool) -> Vec<Candidate> {
        // The best cosine needs only each subject's template count; any other score needs each
        // subject's templates.
        let (scores, counts): (Vec<f32>, Vec<usize>) = if cosine {
            let mut counts = vec![0; self.ids.len()];
            for &owner in &self.owners {
                counts[owner as usize] += 1;
            }
            (self.best_cosines(&probe.vector), counts)
        } else {
            self.rows_by_slot()
                .iter()
                .map(|rows| {
                    let templates: Vec<Template> = rows
                        .iter()
                        .map(|&r| Template { model_version: self.model_version.clone(), vector: self.row(r as usize).to_vec() })
                        .collect();
                    (matcher.score(probe, &templates), rows.len())
                })
                .unzip()
        };
        let mut order: Vec<u32> = (0..self.ids.len() as u32).collect();
        let rank = |a: &u32, b: &u32| {
            scores[*b as usize].total_cmp(&scores[*a as usize]).then_with(|| self.ids[*a as usize].cmp(&self.ids[*b as usize]))
        };
        if k < order.len() {
            order.select_nth_unstable_by(k, rank);
            order.truncate(k);
        }
        order.sort_unstable_by(rank);
        order
            .into_iter()
            .map(|s| {
                let decision = Decision::at(matcher, scores[s as usize], counts[s as usize], fmr);
                Candidate { subject: self.ids[s as usize].to_string(), decision }
            })
            .collect()
    }

    /// Each subject's best cosine with `probe`: one pass over the matrix.
    fn best_cosines(&self, probe: &[f32]) -> Vec<f32> {
        let mut best = vec![f32::NEG_INFINITY; self.ids.len()];
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

    /// The `n` subjects with the best approximate cosine (one scan of the codes), in id order.
    fn shortlist(&self, probe: &[f32], n: usize) -> Vec<String> {
        let probe = codes::QuantisedProbe::new(probe);
        let mut best = codes::Best::new(n);
        codes::scan(&self.codes, &self.scales, &probe, |row, cosine| {
            if cosine > best.floor() {
                best.offer(self.owners[row], cosine);
            }
        });
        let mut subjects: Vec<String> = best.slots().map(|s| self.ids[s as usize].to_string()).collect();
        subjects.sort_unstable();
        subjects
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
