//! The bounded pool the CPU work runs on (decoding, the face pipeline, gallery scoring), and the
//! admission of requests to it.

use std::sync::Arc;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use tokio::sync::Semaphore;

/// Why a job did not run to its end.
#[derive(Debug, thiserror::Error)]
pub enum PoolError {
    /// Every worker is busy and the queue is full: refused at once.
    #[error("the work queue is full; retry shortly")]
    Overloaded,
    /// The job panicked or was cancelled.
    #[error("a pool job failed: {0}")]
    Failed(#[from] tokio::task::JoinError),
}

/// The two admission queues: enrolments have their own, so a flood of verifications cannot
/// starve them of places (once admitted, both wait for the same workers, first come first served).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WorkClass {
    /// Verification, identification and the inspection routes.
    Probe,
    /// Enrolment.
    Enroll,
}

/// A request's place in the pool ([`WorkPool::admit`]), taken by the HTTP layer once the request's
/// body has arrived; its jobs run on this place instead of taking one each. Cheap to clone.
#[derive(Debug, Clone)]
pub struct Admission {
    _place: Arc<tokio::sync::OwnedSemaphorePermit>,
}

tokio::task_local! {
    /// The admission of the request the current task is serving, if it was admitted.
    static ADMITTED: Admission;
}

impl Admission {
    /// Run `future` (the rest of the request) with this admission: [`WorkPool::run`] called inside
    /// it uses the place already held instead of asking for another one.
    pub async fn scope<F: std::future::Future>(self, future: F) -> F::Output {
        ADMITTED.scope(self, future).await
    }
}

/// A bounded pool for CPU work: `workers` jobs run at once on tokio's blocking threads, at most
/// `queue_depth` more probe requests and `enrol_queue_depth` more enrolments wait, and any further
/// one is refused at once with [`PoolError::Overloaded`]. The HTTP layer looks for room with
/// [`WorkPool::admit_within`] before it reads a request's body (a refusal then costs no body read,
/// parse or query) and takes the request's place once the body has arrived.
/// Refusals are counted in `rejections`; queued and running jobs in `in_flight`.
#[derive(Debug, Clone)]
pub struct WorkPool {
    admitted: Arc<Semaphore>,
    enroll_admitted: Arc<Semaphore>,
    running: Arc<Semaphore>,
    rejections: Counter,
    in_flight: Gauge,
}

impl WorkPool {
    pub fn new(workers: usize, queue_depth: usize, enroll_queue_depth: usize, rejections: Counter, in_flight: Gauge) -> WorkPool {
        let workers = workers.max(1);
        WorkPool {
            admitted: Arc::new(Semaphore::new(workers + queue_depth)),
            enroll_admitted: Arc::new(Semaphore::new(workers + enroll_queue_depth)),
            running: Arc::new(Semaphore::new(workers)),
            rejections,
            in_flight,
        }
    }

    /// A place for one request of `class`, or [`PoolError::Overloaded`] at once when its queue is full.
    pub fn admit(&self, class: WorkClass) -> Result<Admission, PoolError> {
        match self.queue(class).clone().try_acquire_owned() {
            Ok(permit) => Ok(Admission { _place: Arc::new(permit) }),
            Err(_) => Err(self.refused()),
        }
    }

    /// [`WorkPool::admit`], waiting up to `wait` for a place when the queue is full. Waiting
    /// requests get places in arrival order (tokio's semaphore is fair), and a client that retries
    /// at once after a 503 cannot come back sooner than `wait`: under a flood, refusals stay few
    /// and cheap, and the workers' throughput stays at its peak.
    pub async fn admit_within(&self, class: WorkClass, wait: std::time::Duration) -> Result<Admission, PoolError> {
        if wait.is_zero() {
            return self.admit(class);
        }
        match tokio::time::timeout(wait, self.queue(class).clone().acquire_owned()).await {
            Ok(permit) => Ok(Admission { _place: Arc::new(permit.expect("the pool's semaphores are never closed")) }),
            Err(_) => Err(self.refused()),
        }
    }

    fn queue(&self, class: WorkClass) -> &Arc<Semaphore> {
        match class {
            WorkClass::Probe => &self.admitted,
            WorkClass::Enroll => &self.enroll_admitted,
        }
    }

    fn refused(&self) -> PoolError {
        self.rejections.inc();
        PoolError::Overloaded
    }

    /// Run `job` on the pool: on the place of the request being served (see [`Admission::scope`]),
    /// else on a probe place taken now. The place moves into the job, so a request that times out
    /// while its job runs still holds it until the job ends: the bound holds.
    pub async fn run<T: Send + 'static>(&self, job: impl FnOnce() -> T + Send + 'static) -> Result<T, PoolError> {
        let admitted = match ADMITTED.try_with(Admission::clone) {
            Ok(admission) => admission,
            Err(_) => self.admit(WorkClass::Probe)?,
        };
        let running = self.running.clone().acquire_owned().await.expect("the pool's semaphores are never closed");
        // Released when the job ends, even by a panic.
        let held = InFlight { _permits: (admitted, running), gauge: self.in_flight.clone() };
        held.gauge.inc();
        // The job runs in the caller's span (a request's), so its stages' spans are the request's.
        let span = tracing::Span::current();
        Ok(tokio::task::spawn_blocking(move || {
            let _held = held;
            span.in_scope(job)
        })
        .await?)
    }
}

struct InFlight {
    _permits: (Admission, tokio::sync::OwnedSemaphorePermit),
    gauge: Gauge,
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.gauge.dec();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_pool_refuses_work_beyond_its_queue() {
        let rejections = Counter::default();
        let pool = WorkPool::new(1, 1, 1, rejections.clone(), Gauge::default());
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let wait = Arc::new(std::sync::Mutex::new(wait));
        let blocker = {
            let (pool, wait) = (pool.clone(), wait.clone());
            tokio::spawn(async move { pool.run(move || wait.lock().unwrap().recv().unwrap()).await })
        };
        // Let the first job take the only worker, then queue a second.
        while pool.running.available_permits() > 0 {
            tokio::task::yield_now().await;
        }
        let queued = {
            let pool = pool.clone();
            tokio::spawn(async move { pool.run(|| 7).await })
        };
        while pool.admitted.available_permits() > 0 {
            tokio::task::yield_now().await;
        }
        assert!(matches!(pool.run(|| 0).await, Err(PoolError::Overloaded)));
        assert_eq!(rejections.get(), 1);
        // The enrolment queue is separate: an enrolment is still admitted, and its job runs on
        // that place (no second one taken) once a worker is free.
        let enrollment = pool.admit(WorkClass::Enroll).unwrap();
        assert!(matches!(pool.admit(WorkClass::Probe), Err(PoolError::Overloaded)));
        let enrolled = {
            let pool = pool.clone();
            tokio::spawn(enrollment.scope(async move { pool.run(|| 9).await }))
        };
        assert_eq!(rejections.get(), 2);
        release.send(()).unwrap();
        blocker.await.unwrap().unwrap();
        assert_eq!(queued.await.unwrap().unwrap(), 7);
        assert_eq!(enrolled.await.unwrap().unwrap(), 9);
        assert!(pool.admit(WorkClass::Enroll).is_ok() && pool.admit(WorkClass::Probe).is_ok());
    }

    #[tokio::test]
    async fn admission_waits_in_order_for_a_place_then_refuses() {
        let pool = WorkPool::new(1, 0, 0, Counter::default(), Gauge::default());
        let held = pool.admit(WorkClass::Probe).unwrap();
        let wait = std::time::Duration::from_millis(50);
        assert!(matches!(pool.admit_within(WorkClass::Probe, wait).await, Err(PoolError::Overloaded)));
        let waiting = {
            let pool = pool.clone();
            tokio::spawn(async move { pool.admit_within(WorkClass::Probe, std::time::Duration::from_secs(5)).await })
        };
        tokio::task::yield_now().await;
        drop(held);
        assert!(waiting.await.unwrap().is_ok());
    }
}
