//! Admission control: a client slot (`limits.max_clients`) is held only by a client whose hello was
//! authenticated. Connections that have not got that far (TLS under way, or a finished handshake and no hello
//! yet) live in a separate, small budget (`max_pending`), each for at most the hello timeout; when the budget is
//! full the *oldest* pending connection is evicted for the newcomer, and when it is half full a newcomer whose
//! address QUIC has not validated is sent a Retry first, so spoofed Initial floods cost one stateless packet.
//! Unauthenticated connections can therefore slow each other down but never hold a slot a valid client needs.

use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, PoisonError};

use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore};

use crate::metrics::Metrics;

/// What to do with a new QUIC connection attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Admit {
    /// Start the handshake (it enters the pending budget).
    Accept,
    /// Answer with a stateless Retry: the peer must prove its address first.
    Retry,
}

#[derive(Debug, Default)]
struct Pending {
    next_id: u64,
    /// Oldest first: (id, its eviction signal).
    queue: VecDeque<(u64, Arc<Notify>)>,
}

/// The two budgets.
#[derive(Debug)]
pub(super) struct Admission {
    max_pending: usize,
    pending: Mutex<Pending>,
    clients: Arc<Semaphore>,
    metrics: Arc<Metrics>,
}

impl Admission {
    pub(super) fn new(max_clients: usize, max_pending: usize, metrics: Arc<Metrics>) -> Arc<Self> {
        Arc::new(Self {
            max_pending: max_pending.max(1),
            pending: Mutex::new(Pending::default()),
            clients: Arc::new(Semaphore::new(max_clients)),
            metrics,
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Pending> {
        self.pending.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Decides about a connection attempt: a Retry when the pending budget is at least half used and the
    /// peer's address is not validated yet (and a Retry is possible), else accept.
    pub(super) fn on_incoming(&self, address_validated: bool, may_retry: bool) -> Admit {
        let under_pressure = 2 * self.lock().queue.len() >= self.max_pending;
        if under_pressure && !address_validated && may_retry {
            self.metrics.pending_retries.fetch_add(1, Ordering::Relaxed);
            Admit::Retry
        } else {
            Admit::Accept
        }
    }

    /// Enters the pending budget; at the budget, the oldest pending connection is told to give way.
    pub(super) fn enter(self: &Arc<Self>) -> PendingSlot {
        let evicted = Arc::new(Notify::new());
        let mut p = self.lock();
        let id = p.next_id;
        p.next_id += 1;
        while p.queue.len() >= self.max_pending {
            if let Some((_, oldest)) = p.queue.pop_front() {
                oldest.notify_one();
                self.metrics.pending_evicted.fetch_add(1, Ordering::Relaxed);
            }
        }
        p.queue.push_back((id, Arc::clone(&evicted)));
        self.metrics
            .pending_connections
            .store(p.queue.len() as i64, Ordering::Relaxed);
        PendingSlot {
            id,
            evicted,
            admission: Arc::clone(self),
        }
    }

    fn leave(&self, id: u64) {
        let mut p = self.lock();
        p.queue.retain(|(i, _)| *i != id);
        self.metrics
            .pending_connections
            .store(p.queue.len() as i64, Ordering::Relaxed);
    }
}

/// A connection's place in the pending budget; leaves it when dropped.
#[derive(Debug)]
pub(super) struct PendingSlot {
    id: u64,
    evicted: Arc<Notify>,
    admission: Arc<Admission>,
}

impl PendingSlot {
    /// Resolves when a newer connection evicted this one.
    pub(super) async fn evicted(&self) {
        self.evicted.notified().await;
    }

    /// The hello was authenticated: leave the pending budget and take a client slot, if one is free.
    pub(super) fn promote(self) -> Option<OwnedSemaphorePermit> {
        Arc::clone(&self.admission.clients).try_acquire_owned().ok()
    }
}

impl Drop for PendingSlot {
    fn drop(&mut self) {
        self.admission.leave(self.id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn admission(clients: usize, pending: usize) -> (Arc<Admission>, Arc<Metrics>) {
        let metrics = Arc::new(Metrics::new(1));
        (Admission::new(clients, pending, Arc::clone(&metrics)), metrics)
    }

    #[tokio::test]
    async fn the_oldest_pending_connection_gives_way_and_slots_go_only_to_authenticated_clients() {
        let (a, m) = admission(1, 2);
        let first = a.enter();
        let second = a.enter();
        assert_eq!(m.pending_connections.load(Ordering::Relaxed), 2);
        let third = a.enter();
        // The first was evicted (its signal fires), the others were not.
        tokio::time::timeout(std::time::Duration::from_millis(100), first.evicted())
            .await
            .expect("the oldest pending connection is evicted");
        assert!(
            tokio::time::timeout(std::time::Duration::from_millis(20), second.evicted())
                .await
                .is_err()
        );
        assert_eq!(m.pending_evicted.load(Ordering::Relaxed), 1);
        drop(first);
        // Pending connections hold no client slot: the one slot goes to the first to authenticate.
        let slot = third.promote().expect("a free client slot");
        assert!(
            second.promote().is_none(),
            "the cap counts authenticated clients only"
        );
        assert_eq!(m.pending_connections.load(Ordering::Relaxed), 0);
        drop(slot);
        assert!(
            a.enter().promote().is_some(),
            "a slot is free again after the client left"
        );
    }

    #[test]
    fn unvalidated_peers_get_a_retry_once_the_budget_is_half_used() {
        let (a, m) = admission(4, 4);
        assert_eq!(a.on_incoming(false, true), Admit::Accept);
        let _p1 = a.enter();
        assert_eq!(a.on_incoming(false, true), Admit::Accept, "1 of 4 pending");
        let _p2 = a.enter();
        assert_eq!(a.on_incoming(false, true), Admit::Retry, "2 of 4 pending");
        assert_eq!(
            a.on_incoming(true, true),
            Admit::Accept,
            "a validated address is accepted"
        );
        assert_eq!(
            a.on_incoming(false, false),
            Admit::Accept,
            "a retried attempt cannot be retried again"
        );
        assert_eq!(m.pending_retries.load(Ordering::Relaxed), 1);
    }
}
