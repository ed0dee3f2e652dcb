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

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, OnceLock, RwLock, Weak};
use std::time::Duration;

use tokio::sync::watch;

use super::{Candidate, Decision, Matcher, SubjectId};
use crate::recognize::Template;
use crate::store::{ChangeFeed, Store, StoreChange, StoreError};

/// Longest an identification waits for the gallery to apply the store's latest change before it
/// searches the gallery as it is (and logs a warning).
const CATCH_UP_WAIT: Duration = Duration::from_secs(2);

/// Pause before a change that failed to apply (the database unreachable) is tried again, as a
/// full reload.
const RETRY_PAUSE: Duration = Duration::from_secs(1);

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

/// Lanes summed separately, so the compiler turns the loop into SIMD multiply-adds (16 lanes:
/// four SSE or two AVX registers) without a reassociation flag.
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    const LANES: usize = 16;
    let mut acc = [0.0f32; LANES];
    let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f32 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in ca.zip(cb) {
        for i in 0..LANES {
            acc[i] += x[i] * y[i];
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// The gallery of the current model version kept in step with the store. Cheap to clone.
#[derive(Clone)]
pub struct LiveGallery(Arc<Live>);

struct Live {
    store: Store,
    gallery: RwLock<Gallery>,
    loaded: tokio::sync::OnceCell<()>,
    /// Enrolments and deletions, one at a time: store commit, then gallery update. Changes from
    /// the feed are applied under it too (store read, then gallery update), so that a local
    /// enrolment's append and a re-read's replacement never interleave.
    writes: tokio::sync::Mutex<()>,
    /// The highest store version the gallery has applied; set when it follows a change feed.
    applied: OnceLock<watch::Receiver<i64>>,
    /// The task applying the change feed.
    follower: std::sync::Mutex<Option<tokio::task::AbortHandle>>,
}

impl Drop for Live {
    fn drop(&mut self) {
        self.stop_following();
    }
}

/// Where the changes made by other processes come from.
enum Changes {
    Feed(ChangeFeed),
    /// A hand-made sequence, for the tests.
    #[cfg(test)]
    Script(tokio::sync::mpsc::UnboundedReceiver<StoreChange>),
}

impl Changes {
    async fn next(&mut self) -> Result<StoreChange, StoreError> {
        match self {
            Changes::Feed(feed) => feed.next().await,
            #[cfg(test)]
            Changes::Script(changes) => changes.recv().await.ok_or_else(|| StoreError::Refused("the script ended".into())),
        }
    }
}

/// Is `error` about the subject's stored data (it stays unreadable until erased), rather than
/// about reaching the database (worth trying again)?
fn unreadable(error: &StoreError) -> bool {
    matches!(error, StoreError::CorruptTemplate { .. } | StoreError::DataKey { .. } | StoreError::NoKey { .. })
}

impl Live {
    /// Abort the task applying the change feed, if one runs.
    fn stop_following(&self) {
        if let Some(task) = self.follower.lock().expect("follower lock").take() {
            task.abort();
        }
    }

    /// The store's templates of the gallery's model version, read afresh; the subjects whose
    /// templates cannot be read are noted in it and returned as `(subject, why)`.
    async fn read_gallery(&self) -> Result<(Gallery, Vec<(String, String)>), StoreError> {
        let version = self.gallery.read().expect("gallery lock").model_version.clone();
        let mut gallery = Gallery::new(&version);
        let mut unreadable = Vec::new();
        self.store
            .gallery(&version, |subject, templates| match templates {
                Ok(templates) => gallery.add(subject, &templates),
                Err(e) => {
                    unreadable.push((subject.to_string(), e.to_string()));
                    gallery.mark_unreadable(subject, e.to_string());
                }
            })
            .await?;
        Ok((gallery, unreadable))
    }

    /// Apply one change from the feed; returns the store version the gallery now reflects.
    async fn apply(&self, change: &StoreChange) -> Result<i64, StoreError> {
        let _writes = self.writes.lock().await;
        match change {
            StoreChange::Subject { subject, version } => {
                let Ok(id) = SubjectId::parse(subject) else {
                    tracing::warn!(subject, "a change notification names an invalid subject id; ignored");
                    return Ok(*version);
                };
                // Read first: a failed read leaves the gallery as it was.
                let templates = match self.store.templates(&id).await {
                    Err(e) if !unreadable(&e) => return Err(e),
                    read => read,
                };
                let mut gallery = self.gallery.write().expect("gallery lock");
                // Replaced, not appended: the store holds all of the subject's templates.
                gallery.remove(subject);
                match templates {
                    Ok(Some(templates)) => gallery.add(subject, &templates),
                    Ok(None) => {}
                    Err(e) => {
                        tracing::error!(subject, "templates cannot be read; /identify refuses until the subject is erased: {e}");
                        gallery.mark_unreadable(subject, e.to_string());
                    }
                }
                Ok(*version)
            }
            StoreChange::Resync => {
                // Read before the reload, so the reload holds at least this version.
                let version = self.store.change_version().await?.unwrap_or(0);
                let (gallery, unreadable) = self.read_gallery().await?;
                for (subject, why) in unreadable {
                    tracing::error!(subject, "templates cannot be read; /identify refuses until the subject is erased: {why}");
                }
                *self.gallery.write().expect("gallery lock") = gallery;
                Ok(version)
            }
        }
    }
}

/// Apply `changes` to the gallery until the gallery is dropped (or a test's script ends). A
/// change that cannot be applied (the database unreachable) is retried as a full reload; a feed
/// that gave up (the database gone for longer than it waits) is opened again, then everything
/// is reloaded.
async fn follow(live: Weak<Live>, mut changes: Changes, applied: watch::Sender<i64>) {
    loop {
        let mut change = match changes.next().await {
            Ok(change) => change,
            Err(e) => {
                #[cfg(test)]
                if let Changes::Script(_) = changes {
                    return;
                }
                tracing::error!("the identify gallery's change feed failed; opening it again: {e}");
                loop {
                    tokio::time::sleep(RETRY_PAUSE).await;
                    let Some(live) = live.upgrade() else { return };
                    match live.store.watch().await {
                        Ok(Some(feed)) => {
                            changes = Changes::Feed(feed);
                            break;
                        }
                        Ok(None) => return,
                        Err(e) => tracing::warn!("cannot open the change feed again: {e}"),
                    }
                }
                StoreChange::Resync
            }
        };
        let version = loop {
            let Some(live) = live.upgrade() else { return };
            match live.apply(&change).await {
                Ok(version) => break version,
                Err(e) => {
                    tracing::warn!("cannot apply a store change to the identify gallery, reloading it in {RETRY_PAUSE:?}: {e}");
                    change = StoreChange::Resync;
                }
            }
            drop(live);
            tokio::time::sleep(RETRY_PAUSE).await;
        };
        applied.send_if_modified(|highest| {
            let newer = version > *highest;
            if newer {
                *highest = version;
            }
            newer
        });
    }
}

impl LiveGallery {
    /// A gallery of `model_version`'s templates in `store`, loaded on [`LiveGallery::load`] or
    /// first use.
    pub fn new(store: Store, model_version: &str) -> LiveGallery {
        LiveGallery(Arc::new(Live {
            store,
            gallery: RwLock::new(Gallery::new(model_version)),
            loaded: tokio::sync::OnceCell::new(),
            writes: tokio::sync::Mutex::new(()),
            applied: OnceLock::new(),
            follower: std::sync::Mutex::new(None),
        }))
    }

    /// Read the store's templates of the model version (once), and from then on follow the
    /// store's change feed where it has one. Subjects whose templates cannot be read are noted
    /// (see [`UnreadableTemplates`]) and returned as `(subject, why)`.
    pub async fn load(&self) -> Result<Vec<(String, String)>, StoreError> {
        let mut unreadable = Vec::new();
        let live = &self.0;
        live.loaded
            .get_or_try_init(|| async {
                // Listening starts before the version and the snapshot are read, so no change
                // committed after them is missed (one committed before is re-read: harmless).
                let feed = live.store.watch().await?;
                let _writes = live.writes.lock().await;
                let version = live.store.change_version().await?;
                let (gallery, cannot_read) = live.read_gallery().await?;
                *live.gallery.write().expect("gallery lock") = gallery;
                unreadable = cannot_read;
                if let (Some(feed), Some(version)) = (feed, version) {
                    self.follow(Changes::Feed(feed), version);
                }
                Ok::<(), StoreError>(())
            })
            .await?;
        Ok(unreadable)
    }

    /// Start applying `changes`, the gallery holding the store's `version`.
    fn follow(&self, changes: Changes, version: i64) {
        let (applied, receiver) = watch::channel(version);
        let task = tokio::spawn(follow(Arc::downgrade(&self.0), changes, applied));
        let _ = self.0.applied.set(receiver);
        *self.0.follower.lock().expect("follower lock") = Some(task.abort_handle());
    }

    /// Stop following the change feed (before the store is closed: the feed holds a connection).
    pub fn stop_following(&self) {
        self.0.stop_following();
    }

    /// The store's version now, where the gallery follows a change feed (one round trip); `None`
    /// when there is nothing to wait for (SQLite: this process is the only writer).
    pub async fn change_version(&self) -> Result<Option<i64>, StoreError> {
        if self.0.applied.get().is_none() {
            return Ok(None);
        }
        self.0.store.change_version().await
    }

    /// Wait until the gallery has applied the store's `version` (from
    /// [`LiveGallery::change_version`]), at most [`CATCH_UP_WAIT`]; after that, or when the feed
    /// has ended, the search goes on with the gallery as it is, and a warning is logged.
    pub async fn wait_until_applied(&self, version: Option<i64>) {
        let (Some(version), Some(applied)) = (version, self.0.applied.get()) else { return };
        let mut applied = applied.clone();
        let waited = tokio::time::timeout(CATCH_UP_WAIT, applied.wait_for(|&v| v >= version)).await.map(|reached| reached.is_ok());
        match waited {
            Ok(true) => {}
            Ok(false) => tracing::warn!(version, "the identify gallery no longer follows the store; searching it as it is"),
            Err(_) => tracing::warn!(
                version,
                applied = *applied.borrow(),
                "the identify gallery has not applied the store's latest change after {CATCH_UP_WAIT:?}; searching it as it is"
            ),
        }
    }

    /// [`Store::enroll`], then the same templates into the gallery.
    pub async fn enroll(&self, subject: &SubjectId, templates: Vec<Template>) -> Result<u32, StoreError> {
        self.load().await?;
        let live = self.0.clone();
        let subject = subject.clone();
        // Spawned, so that a caller dropped mid-way (a request timeout) cannot stop between the
        // commit and the gallery update.
        tokio::spawn(async move {
            let _writes = live.writes.lock().await;
            let count = live.store.enroll(&subject, &templates).await?;
            live.gallery.write().expect("gallery lock").add(subject.as_str(), &templates);
            Ok(count)
        })
        .await
        .expect("the enrolment task does not panic")
    }

    /// [`Store::delete_subject`], then the subject out of the gallery.
    pub async fn delete(&self, subject: &SubjectId) -> Result<Option<u32>, StoreError> {
        self.load().await?;
        let live = self.0.clone();
        let subject = subject.clone();
        tokio::spawn(async move {
            let _writes = live.writes.lock().await;
            let deleted = live.store.delete_subject(&subject).await?;
            live.gallery.write().expect("gallery lock").remove(subject.as_str());
            Ok(deleted)
        })
        .await
        .expect("the deletion task does not panic")
    }

    /// [`Gallery::search`] under the read lock (call it on the work pool: it is CPU work).
    pub fn search(
        &self,
        matcher: &dyn Matcher,
        probe: &Template,
        fmr: f64,
        k: usize,
    ) -> Result<(Vec<Candidate>, usize), UnreadableTemplates> {
        self.0.gallery.read().expect("gallery lock").search(matcher, probe, fmr, k)
    }

    /// Subjects and templates held.
    pub fn size(&self) -> (usize, usize) {
        let gallery = self.0.gallery.read().expect("gallery lock");
        (gallery.subjects(), gallery.templates())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recognize::OperatingPoint;
    use rand::{Rng, SeedableRng};

    /// Scores by the best cosine, like the deep recognizer; `general` turns the fast path off.
    struct Cosine {
        general: bool,
    }

    impl Matcher for Cosine {
        fn model_version(&self) -> &str {
            "v1"
        }
        fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
            enrolled.iter().map(|t| probe.cosine(t)).fold(f32::NEG_INFINITY, f32::max)
        }
        fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
            OperatingPoint { fmr, threshold: 0.5 + 0.01 * enrolled as f32 }
        }
        fn max_cosine_scoring(&self) -> bool {
            !self.general
        }
    }

    /// A matcher whose score is not a cosine (the mean of the first components).
    struct Mean;

    impl Matcher for Mean {
        fn model_version(&self) -> &str {
            "v1"
        }
        fn score(&self, _probe: &Template, enrolled: &[Template]) -> f32 {
            enrolled.iter().map(|t| t.vector[0]).sum::<f32>() / enrolled.len() as f32
        }
        fn operating_point(&self, fmr: f64, _enrolled: usize) -> OperatingPoint {
            OperatingPoint { fmr, threshold: 0.0 }
        }
    }

    fn random_template(rng: &mut impl Rng, version: &str, dims: usize) -> Template {
        Template::new(version, (0..dims).map(|_| rng.random_range(-1.0f32..1.0)).collect())
    }

    fn summary(found: &[Candidate]) -> Vec<(String, usize, bool)> {
        found.iter().map(|c| (c.subject.clone(), c.decision.templates_compared, c.decision.is_match)).collect()
    }

    /// The gallery's answer is `service::identify`'s over the same subjects and templates, through
    /// additions, other versions, zero vectors and removals.
    #[test]
    fn search_equals_identify_through_adds_and_removes() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut gallery = Gallery::new("v1");
        let mut reference: BTreeMap<String, Vec<Template>> = BTreeMap::new();
        for i in 0..300 {
            let subject = format!("s{:03}", i % 120);
            let mut templates = vec![random_template(&mut rng, "v1", 20)];
            if i % 7 == 0 {
                templates.push(random_template(&mut rng, "v0", 20));
            }
            if i == 11 {
                templates.push(Template::new("v1", vec![0.0; 20]));
            }
            gallery.add(&subject, &templates);
            reference.entry(subject).or_default().extend(templates.into_iter().filter(|t| t.model_version == "v1"));
        }
        for i in (0..120).step_by(3) {
            let subject = format!("s{i:03}");
            gallery.remove(&subject);
            reference.remove(&subject);
        }
        gallery.remove("nobody");
        assert_eq!(gallery.subjects(), reference.len());
        assert_eq!(gallery.templates(), reference.values().map(Vec::len).sum::<usize>());
        for trial in 0..20 {
            let probe = random_template(&mut rng, "v1", 20);
            let k = [1, 5, 100, 1000][trial % 4];
            let expected = crate::service::identify(&Cosine { general: true }, &probe, reference.clone().into_iter().collect(), 1e-3, k);
            for general in [false, true] {
                let (found, searched) = gallery.search(&Cosine { general }, &probe, 1e-3, k).unwrap();
                assert_eq!(searched, reference.len());
                assert_eq!(summary(&found), summary(&expected), "general path: {general}");
                for (a, b) in found.iter().zip(&expected) {
                    assert!((a.decision.score - b.decision.score).abs() < 1e-5, "{} vs {}", a.decision.score, b.decision.score);
                    assert_eq!(a.decision.threshold, b.decision.threshold);
                }
            }
            // A matcher that is not a cosine scores through its own `score`.
            let expected = crate::service::identify(&Mean, &probe, reference.clone().into_iter().collect(), 1e-3, k);
            let (found, _) = gallery.search(&Mean, &probe, 1e-3, k).unwrap();
            assert_eq!(found, expected);
        }
        // Everything removed: an empty gallery answers with no candidate.
        for subject in reference.keys() {
            gallery.remove(subject);
        }
        assert_eq!((gallery.subjects(), gallery.templates(), gallery.vectors.len()), (0, 0, 0));
        assert!(gallery.search(&Cosine { general: false }, &random_template(&mut rng, "v1", 20), 1e-3, 5).unwrap().0.is_empty());
    }

    #[test]
    fn unreadable_subjects_refuse_the_search_until_erased() {
        let mut gallery = Gallery::new("v1");
        gallery.add("alice", &[Template::new("v1", vec![1.0, 0.0])]);
        gallery.mark_unreadable("bob", "authentication failed".into());
        let probe = Template::new("v1", vec![1.0, 0.0]);
        let err = gallery.search(&Cosine { general: false }, &probe, 1e-3, 5).unwrap_err();
        assert_eq!(err, UnreadableTemplates { count: 1, first: "bob".into() });
        // A template of another dimension is not comparable: the subject is unreadable too.
        gallery.add("carol", &[Template::new("v1", vec![1.0, 0.0, 0.0])]);
        gallery.remove("bob");
        assert!(gallery.search(&Cosine { general: false }, &probe, 1e-3, 5).is_err());
        gallery.remove("carol");
        let (found, searched) = gallery.search(&Cosine { general: false }, &probe, 1e-3, 5).unwrap();
        assert_eq!((found[0].subject.as_str(), searched), ("alice", 1));
    }

    /// Concurrent enrolments and deletions of the same subjects, some of them cancelled by their
    /// caller: afterwards the live gallery answers as one loaded afresh from the store.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_live_gallery_stays_in_step_with_the_store() {
        let dir = std::env::temp_dir().join(format!("facegate-gallery-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let url = format!("sqlite://{}", dir.join("g.db").display());
        let store = Store::connect(&url, None).await.unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        store.enroll(&SubjectId::parse("before").unwrap(), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
        let live = LiveGallery::new(store.clone(), "v1");
        let mut tasks = Vec::new();
        for i in 0..120 {
            let live = live.clone();
            let subject = SubjectId::parse(&format!("s{}", i % 9)).unwrap();
            let templates = vec![random_template(&mut rng, "v1", 16), random_template(&mut rng, "v0", 16)];
            tasks.push(tokio::spawn(async move {
                let work = async {
                    if i % 4 == 3 { live.delete(&subject).await.map(|_| ()) } else { live.enroll(&subject, templates).await.map(|_| ()) }
                };
                if i % 5 == 0 {
                    // The caller gives up at once; what it started still completes or never starts.
                    let _ = tokio::time::timeout(std::time::Duration::from_micros(50), work).await;
                } else {
                    work.await.unwrap();
                }
            }));
        }
        for task in tasks {
            task.await.unwrap();
        }
        // Wait for any enrolment or deletion a cancelled caller left running (spawned: they get
        // to the writes lock, which is fair, soon after).
        tokio::time::sleep(std::time::Duration::from_millis(300)).await;
        drop(live.0.writes.lock().await);
        let fresh = LiveGallery::new(store.clone(), "v1");
        assert!(fresh.load().await.unwrap().is_empty());
        assert_eq!(live.size(), fresh.size());
        let (subjects, templates) = store.counts().await.unwrap();
        // Each enrolment stored one template of each version; `before` has one of v1 only.
        assert_eq!((live.size().0 as u64, live.size().1 as u64 * 2 - 1), (subjects, templates));
        for _ in 0..10 {
            let probe = random_template(&mut rng, "v1", 16);
            let matcher = Cosine { general: false };
            assert_eq!(live.search(&matcher, &probe, 1e-3, 20).unwrap(), fresh.search(&matcher, &probe, 1e-3, 20).unwrap());
        }
        store.close().await;
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// The store version the gallery has applied, when it follows a feed.
    fn applied(live: &LiveGallery) -> Option<i64> {
        live.0.applied.get().map(|applied| *applied.borrow())
    }

    /// Another writer changes the store and a hand-made feed tells of it: each subject is re-read
    /// (replaced, not appended; removed when gone; unreadable noted until erased), a resync reads
    /// everything, the highest version is tracked, and the end of the feed ends the waits.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_live_gallery_follows_a_change_feed() {
        let dir = std::env::temp_dir().join(format!("facegate-gallery-feed-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let url = format!("sqlite://{}", dir.join("g.db").display());
        let keys = crate::store::KeyRing::parse(&"5a".repeat(32)).unwrap();
        // The other replica has the template key; this one's store is opened without it, so a
        // subject the other seals is unreadable here.
        let other = Store::connect(&url, Some(keys)).await.unwrap();
        let store = Store::connect(&url, None).await.unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let id = |s: &str| SubjectId::parse(s).unwrap();
        let live = LiveGallery::new(store.clone(), "v1");
        assert!(live.load().await.unwrap().is_empty());
        assert_eq!((applied(&live), live.change_version().await.unwrap()), (None, None), "SQLite: no feed, nothing to wait for");
        let (changes, script) = tokio::sync::mpsc::unbounded_channel();
        live.follow(Changes::Script(script), 0);
        let notify = |subject: &str, version: i64| changes.send(StoreChange::Subject { subject: subject.into(), version }).unwrap();
        let matcher = Cosine { general: false };

        let alice = random_template(&mut rng, "v1", 16);
        store.enroll(&id("alice"), &[alice.clone(), random_template(&mut rng, "v0", 16)]).await.unwrap();
        notify("alice", 1);
        live.wait_until_applied(Some(1)).await;
        assert_eq!((applied(&live), live.size()), (Some(1), (1, 1)), "only the gallery's model version");
        assert_eq!(live.search(&matcher, &alice, 1e-3, 1).unwrap().0[0].subject, "alice");
        store.enroll(&id("alice"), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
        notify("alice", 2);
        // The notification of a write already applied (this replica's own) changes nothing.
        notify("alice", 2);
        notify("alice", 1);
        live.wait_until_applied(Some(2)).await;
        assert_eq!((applied(&live), live.size()), (Some(2), (1, 2)), "re-read, not appended");
        store.delete_subject(&id("alice")).await.unwrap();
        notify("alice", 3);
        live.wait_until_applied(Some(3)).await;
        assert_eq!(live.size(), (0, 0));

        other.enroll(&id("dave"), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
        notify("dave", 4);
        live.wait_until_applied(Some(4)).await;
        let err = live.search(&matcher, &alice, 1e-3, 1).unwrap_err();
        assert_eq!(err, UnreadableTemplates { count: 1, first: "dave".into() });
        other.delete_subject(&id("dave")).await.unwrap();
        notify("dave", 5);
        live.wait_until_applied(Some(5)).await;
        assert!(live.search(&matcher, &alice, 1e-3, 1).unwrap().0.is_empty());

        // Changes whose notifications were lost: a resync reads them all.
        for name in ["bob", "carol"] {
            store.enroll(&id(name), &[random_template(&mut rng, "v1", 16)]).await.unwrap();
        }
        changes.send(StoreChange::Resync).unwrap();
        notify("nobody", 6);
        live.wait_until_applied(Some(6)).await;
        assert_eq!((applied(&live), live.size()), (Some(6), (2, 2)));
        let fresh = LiveGallery::new(store.clone(), "v1");
        fresh.load().await.unwrap();
        let probe = random_template(&mut rng, "v1", 16);
        assert_eq!(live.search(&matcher, &probe, 1e-3, 5).unwrap(), fresh.search(&matcher, &probe, 1e-3, 5).unwrap());

        // The feed ends: waiting for a version never applied returns at once.
        drop(changes);
        tokio::time::sleep(Duration::from_millis(50)).await;
        let start = std::time::Instant::now();
        live.wait_until_applied(Some(100)).await;
        assert!(start.elapsed() < Duration::from_secs(1), "{:?}", start.elapsed());
        live.stop_following();
        other.close().await;
        store.close().await;
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// A version the gallery never applies is waited for at most [`CATCH_UP_WAIT`].
    #[tokio::test]
    async fn waiting_for_the_gallery_is_bounded() {
        let dir = std::env::temp_dir().join(format!("facegate-gallery-wait-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let store = Store::connect(&format!("sqlite://{}", dir.join("g.db").display()), None).await.unwrap();
        let live = LiveGallery::new(store.clone(), "v1");
        let (_changes, script) = tokio::sync::mpsc::unbounded_channel();
        live.follow(Changes::Script(script), 7);
        let start = std::time::Instant::now();
        live.wait_until_applied(Some(7)).await;
        assert!(start.elapsed() < Duration::from_millis(100));
        live.wait_until_applied(Some(8)).await;
        let waited = start.elapsed();
        assert!(waited >= CATCH_UP_WAIT && waited < CATCH_UP_WAIT + Duration::from_secs(1), "{waited:?}");
        live.stop_following();
        store.close().await;
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn the_dot_product_sums_every_value() {
        for n in [1, 15, 16, 17, 128, 130] {
            let a: Vec<f32> = (0..n).map(|i| i as f32).collect();
            let b = vec![2.0f32; n];
            assert_eq!(dot(&a, &b), (n * (n - 1)) as f32, "{n}");
        }
    }
}
