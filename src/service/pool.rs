//! The bounded pool the CPU work runs on (decoding, the face pipeline, gallery scoring).

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

/// A bounded pool for CPU work: `workers` jobs run at once on tokio's blocking threads, at most
/// `queue_depth` more wait, and any further job is refused at once with [`PoolError::Overloaded`].
/// Refusals are counted in `rejections`; queued and running jobs in `in_flight`.
#[derive(Debug, Clone)]
pub struct WorkPool {
    admitted: Arc<Semaphore>,
    running: Arc<Semaphore>,
    rejections: Counter,
    in_flight: Gauge,
}

impl WorkPool {
    pub fn new(workers: usize, queue_depth: usize, rejections: Counter, in_flight: Gauge) -> WorkPool {
        let workers = workers.max(1);
        WorkPool {
            admitted: Arc::new(Semaphore::new(workers + queue_depth)),
            running: Arc::new(Semaphore::new(workers)),
            rejections,
            in_flight,
        }
    }

    /// Run `job` on the pool. The permits move into the job, so a request that times out while
    /// its job runs still holds its place until the job ends: the bound holds.
    pub async fn run<T: Send + 'static>(&self, job: impl FnOnce() -> T + Send + 'static) -> Result<T, PoolError> {
        let Ok(admitted) = self.admitted.clone().try_acquire_owned() else {
            self.rejections.inc();
            return Err(PoolError::Overloaded);
        };
        let running = self.running.clone().acquire_owned().await.expect("the pool's semaphores are never closed");
        // Released when the job ends, even by a panic.
        let held = InFlight { _permits: (admitted, running), gauge: self.in_flight.clone() };
        held.gauge.inc();
        Ok(tokio::task::spawn_blocking(move || {
            let _held = held;
            job()
        })
        .await?)
    }
}

struct InFlight {
    _permits: (tokio::sync::OwnedSemaphorePermit, tokio::sync::OwnedSemaphorePermit),
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
        let pool = WorkPool::new(1, 1, rejections.clone(), Gauge::default());
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
        release.send(()).unwrap();
        blocker.await.unwrap().unwrap();
        assert_eq!(queued.await.unwrap().unwrap(), 7);
    }
}
