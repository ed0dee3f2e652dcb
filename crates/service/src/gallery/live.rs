//! [`LiveGallery`]: the [`Gallery`] kept in step with the [`Store`] and, where other processes
//! write to the same database, with its change feed.

use std::sync::{Arc, OnceLock, RwLock, Weak};
use std::time::Duration;

use tokio::sync::watch;

use super::{Found, Gallery, Precision, UnreadableTemplates};
use crate::{Candidate, Matcher, SubjectId};
use facegate_core::template::Template;
use facegate_store::{ChangeFeed, Store, StoreChange, StoreError};

/// Longest an identification waits for the gallery to apply the store's latest change before it
/// searches the gallery as it is (and logs a warning).
const CATCH_UP_WAIT: Duration = Duration::from_secs(2);

/// Connections that read the gallery at start-up, each a part of the subjects: one per core (2 to
/// 8), so that the rows' decoding and quantising run on every core (docs/gallery.md measures the
/// load).
fn load_parts() -> usize {
    std::thread::available_parallelism().map_or(2, |n| n.get()).clamp(2, 8)
}

/// Pause before a change that failed to apply (the database unreachable) is tried again, as a
/// full reload.
const RETRY_PAUSE: Duration = Duration::from_secs(1);

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
pub(super) enum Changes {
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

    /// The store's templates of the gallery's model version, read afresh by [`load_parts`]
    /// connections at once (each part of the subjects into a gallery of its own on its own task,
    /// then joined in id order onto the first); the subjects whose templates cannot be read are noted in it and
    /// returned as `(subject, why)`.
    async fn read_gallery(&self) -> Result<(Gallery, Vec<(String, String)>), StoreError> {
        let (version, precision) = {
            let gallery = self.gallery.read().expect("gallery lock");
            (gallery.model_version.clone(), gallery.precision)
        };
        let parts = self.store.gallery_parts(&version, load_parts()).await?;
        let readers: Vec<_> = parts
            .into_iter()
            .map(|part| {
                let (store, version) = (self.store.clone(), version.clone());
                tokio::spawn(async move {
                    let mut gallery = Gallery::with_precision(&version, precision);
                    gallery.reserve(part.expected_templates);
                    let part_gallery = (gallery, Vec::new());
                    store
                        .gallery_part(&version, &part, part_gallery, |(gallery, unreadable), subject, templates| match templates {
                            Ok(templates) => gallery.add(subject, &templates),
                            Err(e) => {
                                unreadable.push((subject.to_string(), e.to_string()));
                                gallery.mark_unreadable(subject, e.to_string());
                            }
                        })
                        .await
                })
            })
            .collect();
        let mut gallery: Option<Gallery> = None;
        let mut unreadable = Vec::new();
        for reader in readers {
            let (part, cannot_read) = reader.await.expect("a gallery reader does not panic")?;
            match &mut gallery {
                Some(gallery) => gallery.absorb(part),
                None => gallery = Some(part),
            }
            unreadable.extend(cannot_read);
        }
        Ok((gallery.unwrap_or_else(|| Gallery::with_precision(&version, precision)), unreadable))
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
    /// A gallery of `model_version`'s templates in `store`, held at `precision`, loaded on
    /// [`LiveGallery::load`] or first use.
    pub fn new(store: Store, model_version: &str, precision: Precision) -> LiveGallery {
        LiveGallery(Arc::new(Live {
            store,
            gallery: RwLock::new(Gallery::with_precision(model_version, precision)),
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
    pub(super) fn follow(&self, changes: Changes, version: i64) {
        let (applied, receiver) = watch::channel(version);
        let task = tokio::spawn(follow(Arc::downgrade(&self.0), changes, applied));
        let _ = self.0.applied.set(receiver);
        *self.0.follower.lock().expect("follower lock") = Some(task.abort_handle());
    }

    /// Has [`LiveGallery::load`] read the store?
    pub fn is_loaded(&self) -> bool {
        self.0.loaded.initialized()
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
        // The write must begin within the store's acquire bound from now, however long it waits
        // behind other writers: while the database is down none is held longer.
        let begin_by = tokio::time::Instant::now() + facegate_store::ACQUIRE_TIMEOUT;
        let live = self.0.clone();
        let subject = subject.clone();
        // Spawned, so that a caller dropped mid-way (a request timeout) cannot stop between the
        // commit and the gallery update.
        tokio::spawn(async move {
            let _writes = live.writes.lock().await;
            let count = live.store.enroll_by(&subject, &templates, begin_by).await?;
            live.gallery.write().expect("gallery lock").add(subject.as_str(), &templates);
            Ok(count)
        })
        .await
        .expect("the enrolment task does not panic")
    }

    /// [`Store::delete_subject`], then the subject out of the gallery.
    pub async fn delete(&self, subject: &SubjectId) -> Result<Option<u32>, StoreError> {
        self.load().await?;
        let begin_by = tokio::time::Instant::now() + facegate_store::ACQUIRE_TIMEOUT;
        let live = self.0.clone();
        let subject = subject.clone();
        tokio::spawn(async move {
            let _writes = live.writes.lock().await;
            let deleted = live.store.delete_subject_by(&subject, begin_by).await?;
            live.gallery.write().expect("gallery lock").remove(subject.as_str());
            Ok(deleted)
        })
        .await
        .expect("the deletion task does not panic")
    }

    /// [`Gallery::search`] under the read lock (call it on the work pool: it is CPU work).
    pub fn search(&self, matcher: &dyn Matcher, probe: &Template, fmr: f64, k: usize) -> Result<(Found, usize), UnreadableTemplates> {
        self.0.gallery.read().expect("gallery lock").search(matcher, probe, fmr, k)
    }

    /// The answer of a search ([`LiveGallery::search`]): an exact gallery's candidates as they
    /// are; a quantised gallery's shortlist scored exactly, its subjects' templates of the
    /// matcher's model version read from the store in one statement (in id order; a subject
    /// deleted since is left out), then the best `k` by [`super::score_each_subject`], so that
    /// ties go by id as in an exact search.
    pub async fn rerank(
        &self,
        matcher: &(dyn Matcher + Sync),
        probe: &Template,
        found: Found,
        fmr: f64,
        k: usize,
    ) -> Result<Vec<Candidate>, StoreError> {
        let shortlist = match found {
            Found::Decided(candidates) => return Ok(candidates),
            Found::Shortlist(shortlist) => shortlist,
        };
        let ids: Vec<SubjectId> = shortlist.iter().filter_map(|s| SubjectId::parse(s).ok()).collect();
        let scored = self.0.store.templates_of(&ids, matcher.model_version()).await?;
        Ok(super::score_each_subject(matcher, probe, scored, fmr, k))
    }

    /// [`LiveGallery::search`] then [`LiveGallery::rerank`]: the answer of `/identify` (the
    /// service runs the search on its work pool; this is for tests and tools).
    pub async fn identify(
        &self,
        matcher: &(dyn Matcher + Sync),
        probe: &Template,
        fmr: f64,
        k: usize,
    ) -> Result<Result<(Vec<Candidate>, usize), UnreadableTemplates>, StoreError> {
        let (found, searched) = match self.search(matcher, probe, fmr, k) {
            Ok(found) => found,
            Err(e) => return Ok(Err(e)),
        };
        Ok(Ok((self.rerank(matcher, probe, found, fmr, k).await?, searched)))
    }

    /// Subjects and templates held.
    pub fn size(&self) -> (usize, usize) {
        let gallery = self.0.gallery.read().expect("gallery lock");
        (gallery.subjects(), gallery.templates())
    }
}

#[cfg(test)]
mod tests;
