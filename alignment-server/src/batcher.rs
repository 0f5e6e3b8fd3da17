//! The dynamic batcher: an IO-free state machine that groups frames from many
//! clients into inference batches.
//!
//! It never reads a clock, sleeps or touches a socket: every call that depends
//! on time takes `now`, and [`DynamicBatcher::poll_timeout`] tells the driver
//! when it must call back. Call order for a driver (see `server/scheduler.rs`):
//!
//! 1. [`DynamicBatcher::push`] every frame as it arrives.
//! 2. When the timer from [`DynamicBatcher::poll_timeout`] fires, call
//!    [`DynamicBatcher::handle_timeout`].
//! 3. After every input, drain [`DynamicBatcher::poll_dropped`] (answer those
//!    frames with `Dropped{reason}`), then, if the engine is idle, call
//!    [`DynamicBatcher::poll_batch`] and hand the batch to the engine.
//! 4. Re-arm the timer with [`DynamicBatcher::poll_timeout`] when the engine
//!    is idle, or [`DynamicBatcher::next_expiry`] while it is busy.
//!
//! # Policy
//!
//! * **Bounded per face**: a queue is keyed by (client, track): one headset
//!   sends a crop per tracked face per frame, each under its face's track id
//!   (protocol version 3; older clients send track 0 only). Each key has a
//!   FIFO of at most `per_client_queue` crops; a newer crop evicts the oldest
//!   ([`DropReason::Superseded`]), and a crop older than one already queued
//!   for the same key is superseded on arrival, so a newer crop of one face
//!   never drops another face's. A global bound (`max_queued`) sheds new
//!   crops with [`DropReason::Overloaded`]. (What one client may have queued
//!   in all is bounded before the batcher: each queued crop holds one of its
//!   `max_in_flight` frame streams.)
//! * **Deadlines**: a frame whose deadline has passed is dropped with
//!   [`DropReason::Expired`] and never reaches the engine.
//! * **When to fire** ([`BatchPolicy`]): the driver asks for a batch only
//!   when the engine is idle. Under [`BatchPolicy::WorkConserving`] (the
//!   default) an idle engine takes whatever is queued at once, so a lone
//!   headset pays no batching delay, and batches grow only while the engine is
//!   busy (frames that arrive during an inference form the next batch). Under
//!   [`BatchPolicy::MaxWait`] a partial batch waits until its oldest frame has
//!   waited `max_wait` (fuller batches at the cost of latency). Either way a
//!   batch fires as soon as `max_batch` frames are queued.
//! * **Fair shares per client, then per face**: batches are filled by
//!   round robin over the clients with queued crops and, within a client,
//!   over its faces; the rotations continue across batches, so a deep queue
//!   cannot starve others. A client alone (no other client pushed within
//!   [`ACTIVE_WINDOW`]) fills whole batches. While several are active, a
//!   batch takes at most one crop per client (a quantum of one crop: every
//!   crop costs the engine about the same on a CPU), and a client with a
//!   backlog that was in the last batch sits the next one out when another
//!   client has a crop waiting. So a client's share of the engine does not
//!   grow with its number of faces, and a crop never waits behind more than
//!   one other client's batch. The price: while several clients are active,
//!   batches hold at most one crop per client, which on an engine whose
//!   batch cost is nearly flat (a GPU) gives up throughput that larger
//!   batches would have bought; an engine is never left idle while a crop is
//!   queued.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use holoface_protocol::DropReason;

/// Identifies a client (one QUIC connection) inside the server.
pub type ClientId = u64;

/// One face of one client: what supersede, expiry and fairness are keyed by.
pub type QueueKey = (ClientId, u16);

/// A client that pushed a crop within this long is active: while more than one is, each puts at most one
/// crop in a batch, so one headset's many faces cannot hold the engine for a whole batch while another
/// headset waits. Three frame intervals at 30 fps.
pub const ACTIVE_WINDOW: Duration = Duration::from_millis(100);

/// When an idle engine gets a partial batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BatchPolicy {
    /// At once: the engine never idles while a frame waits; batches fill while it is busy.
    #[default]
    WorkConserving,
    /// When the oldest queued frame has waited this long (or the batch is full).
    MaxWait(Duration),
}

/// Batcher limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatcherConfig {
    /// Largest batch handed to the engine (>= 1).
    pub max_batch: usize,
    /// When a partial batch goes to an idle engine.
    pub policy: BatchPolicy,
    /// Frames kept per client (>= 1); older ones are superseded.
    pub per_client_queue: usize,
    /// Frames kept in total; beyond it new frames are shed as overloaded.
    pub max_queued: usize,
}

impl Default for BatcherConfig {
    fn default() -> Self {
        Self {
            max_batch: 8,
            policy: BatchPolicy::WorkConserving,
            per_client_queue: 1,
            max_queued: 4096,
        }
    }
}

/// One queued frame.
#[derive(Debug)]
pub struct Pending<T> {
    /// The client that sent it.
    pub client: ClientId,
    /// Which of the client's faces it is (the request's track id; 0 for a one-face client).
    pub track: u16,
    /// The client's frame number (strictly increasing per track).
    pub frame_id: u64,
    /// When it arrived at the server.
    pub arrived: Instant,
    /// When it stops being worth aligning.
    pub expires: Instant,
    /// Whatever the driver needs to answer it (pixels, reply handle).
    pub payload: T,
}

/// A frame the batcher gave up on, and why.
#[derive(Debug)]
pub struct Dropped<T> {
    /// The frame.
    pub item: Pending<T>,
    /// Why it was dropped.
    pub reason: DropReason,
}

/// Frames to run through the engine together.
#[derive(Debug)]
pub struct Batch<T> {
    /// The frames, at most `max_batch`, in round-robin (client, track) order.
    pub items: Vec<Pending<T>>,
    /// When the batch was formed (the `now` passed to `poll_batch`).
    pub formed_at: Instant,
}

/// The sans-IO dynamic batcher. See the module docs for the call order and
/// the policy.
#[derive(Debug)]
pub struct DynamicBatcher<T> {
    cfg: BatcherConfig,
    queues: HashMap<QueueKey, VecDeque<Pending<T>>>,
    /// Clients with at least one non-empty queue, in service order.
    clients: VecDeque<ClientId>,
    /// Per client in `clients`: its faces with a non-empty queue, in service order.
    faces: HashMap<ClientId, VecDeque<u16>>,
    /// When each client last pushed a crop: the clients seen within [`ACTIVE_WINDOW`] share the engine.
    last_push: HashMap<ClientId, Instant>,
    /// The clients of the last batch.
    last_batch: Vec<ClientId>,
    len: usize,
    dropped: VecDeque<Dropped<T>>,
    draining: bool,
}

impl<T> DynamicBatcher<T> {
    /// A batcher with the given limits (zero limits are raised to 1).
    pub fn new(mut cfg: BatcherConfig) -> Self {
        cfg.max_batch = cfg.max_batch.max(1);
        cfg.per_client_queue = cfg.per_client_queue.max(1);
        cfg.max_queued = cfg.max_queued.max(1);
        Self {
            cfg,
            queues: HashMap::new(),
            clients: VecDeque::new(),
            faces: HashMap::new(),
            last_push: HashMap::new(),
            last_batch: Vec::new(),
            len: 0,
            dropped: VecDeque::new(),
            draining: false,
        }
    }

    /// The limits in force.
    pub const fn config(&self) -> &BatcherConfig {
        &self.cfg
    }

    /// Frames currently queued.
    pub const fn len(&self) -> usize {
        self.len
    }

    /// `true` when no frame is queued.
    pub const fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Queues a frame that arrived at `now`. Frames it displaces (or the
    /// frame itself, if stale or over a bound) come out of
    /// [`Self::poll_dropped`].
    pub fn push(&mut self, item: Pending<T>, now: Instant) {
        if self.draining {
            return self.drop_item(item, DropReason::ShuttingDown);
        }
        self.last_push.insert(item.client, now);
        if item.expires <= now {
            return self.drop_item(item, DropReason::Expired);
        }
        let key = (item.client, item.track);
        let queue = self.queues.entry(key).or_default();
        if queue
            .back()
            .is_some_and(|newest| newest.frame_id >= item.frame_id)
        {
            // An older crop of this face arriving after a newer one (streams
            // complete out of order): the newer one already supersedes it.
            return self.drop_item(item, DropReason::Superseded);
        }
        let was_empty = queue.is_empty();
        let mut evicted = None;
        if queue.len() >= self.cfg.per_client_queue {
            evicted = queue.pop_front();
        } else if self.len >= self.cfg.max_queued {
            if was_empty {
                // Nothing queued for this face: forget its empty queue, so a client cycling through track
                // ids while the server is overloaded cannot grow the map.
                self.queues.remove(&key);
            }
            return self.drop_item(item, DropReason::Overloaded);
        }
        queue.push_back(item);
        if let Some(old) = evicted {
            self.dropped.push_back(Dropped {
                item: old,
                reason: DropReason::Superseded,
            });
        } else {
            self.len += 1;
        }
        if was_empty {
            self.enqueue_face(key);
        }
    }

    /// Drops every queued frame whose deadline is at or before `now`.
    pub fn handle_timeout(&mut self, now: Instant) {
        let mut emptied = false;
        for queue in self.queues.values_mut() {
            let before = queue.len();
            let mut kept = VecDeque::with_capacity(before);
            while let Some(item) = queue.pop_front() {
                if item.expires <= now {
                    self.dropped.push_back(Dropped {
                        item,
                        reason: DropReason::Expired,
                    });
                } else {
                    kept.push_back(item);
                }
            }
            self.len -= before - kept.len();
            emptied |= before > 0 && kept.is_empty();
            *queue = kept;
        }
        if emptied {
            self.prune();
        }
    }

    /// Next frame the driver must answer with `Dropped{reason}`.
    pub fn poll_dropped(&mut self) -> Option<Dropped<T>> {
        self.dropped.pop_front()
    }

    /// A batch, if one is due at `now` (call it when the engine is idle): any
    /// queued frame under [`BatchPolicy::WorkConserving`]; under
    /// [`BatchPolicy::MaxWait`], `max_batch` frames queued or the oldest having
    /// waited `max_wait`. Expired frames are dropped first.
    pub fn poll_batch(&mut self, now: Instant) -> Option<Batch<T>> {
        self.handle_timeout(now);
        if self.len == 0 {
            return None;
        }
        let due = self.len >= self.cfg.max_batch || self.flush_at().is_some_and(|t| t <= now);
        if !due {
            return None;
        }
        // A batch holds the engine until its last crop is done, and a crop that arrives meanwhile waits for
        // all of it. So while several clients are active, a batch takes one crop per client (a client's
        // quantum), and a client with a backlog (several faces waiting) that was in the last batch sits
        // this one out when another client has a crop waiting: the engine alternates between the clients,
        // not between their faces, and a one-face headset waits for at most one other crop.
        self.last_push
            .retain(|_, t| now.saturating_duration_since(*t) <= ACTIVE_WINDOW);
        let shared = self.last_push.len() > 1;
        let quantum = if shared { 1 } else { self.cfg.max_batch };
        let last_batch = std::mem::take(&mut self.last_batch);
        let skip: Vec<ClientId> = if shared && self.clients.iter().any(|c| !last_batch.contains(c)) {
            last_batch
                .into_iter()
                .filter(|&c| self.queued_of(c) > 1)
                .collect()
        } else {
            Vec::new()
        };
        let mut taken: HashMap<ClientId, usize> = HashMap::new();
        let mut items = Vec::with_capacity(self.cfg.max_batch.min(self.len));
        while items.len() < self.cfg.max_batch {
            let may_take = |c: ClientId| !skip.contains(&c) && taken.get(&c).copied().unwrap_or(0) < quantum;
            let Some(item) = self.next_crop(may_take) else {
                break;
            };
            *taken.entry(item.client).or_default() += 1;
            items.push(item);
        }
        self.last_batch = taken.into_keys().collect();
        Some(Batch {
            items,
            formed_at: now,
        })
    }

    /// When the driver must call back ([`Self::poll_batch`] for the
    /// `max_wait` flush, [`Self::handle_timeout`] for the earliest deadline),
    /// or `None` when nothing is queued.
    pub fn poll_timeout(&self) -> Option<Instant> {
        let flush = self.flush_at();
        let expiry = self
            .queues
            .values()
            .flat_map(|q| q.iter().map(|i| i.expires))
            .min();
        match (flush, expiry) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// The earliest deadline of a queued frame. While the engine is busy a
    /// driver cannot act on the flush time, so it arms its timer with this
    /// instead of [`Self::poll_timeout`] (an already-passed flush time would
    /// otherwise wake it in a loop).
    pub fn next_expiry(&self) -> Option<Instant> {
        self.queues
            .values()
            .flat_map(|q| q.iter().map(|i| i.expires))
            .min()
    }

    /// Forgets a client that went away; its queued frames (of every track)
    /// are discarded without a reply (there is nobody to answer). Returns how many.
    pub fn remove_client(&mut self, client: ClientId) -> usize {
        let mut n = 0;
        self.queues.retain(|(c, _), q| {
            let gone = *c == client;
            if gone {
                n += q.len();
            }
            !gone
        });
        self.len -= n;
        self.clients.retain(|c| *c != client);
        self.faces.remove(&client);
        self.last_push.remove(&client);
        n
    }

    /// Starts draining for shutdown: every queued frame and every later push
    /// is dropped with [`DropReason::ShuttingDown`]. A batch already handed
    /// to the engine is unaffected.
    pub fn start_drain(&mut self) {
        self.draining = true;
        for (_, queue) in self.queues.drain() {
            for item in queue {
                self.dropped.push_back(Dropped {
                    item,
                    reason: DropReason::ShuttingDown,
                });
            }
        }
        self.clients.clear();
        self.faces.clear();
        self.len = 0;
    }

    /// `true` after [`Self::start_drain`].
    pub const fn is_draining(&self) -> bool {
        self.draining
    }

    fn drop_item(&mut self, item: Pending<T>, reason: DropReason) {
        self.dropped.push_back(Dropped { item, reason });
    }

    /// When a partial batch becomes due (the oldest arrival under work-conserving batching).
    fn flush_at(&self) -> Option<Instant> {
        let wait = match self.cfg.policy {
            BatchPolicy::WorkConserving => Duration::ZERO,
            BatchPolicy::MaxWait(w) => w,
        };
        self.oldest_arrival().map(|t| t + wait)
    }

    fn oldest_arrival(&self) -> Option<Instant> {
        self.queues
            .values()
            .filter_map(|q| q.front().map(|i| i.arrived))
            .min()
    }

    /// Crops `client` has queued, over all its faces.
    fn queued_of(&self, client: ClientId) -> usize {
        self.faces.get(&client).map_or(0, |faces| {
            faces
                .iter()
                .map(|&t| self.queues.get(&(client, t)).map_or(0, VecDeque::len))
                .sum()
        })
    }

    /// Puts a face whose queue just became non-empty at the back of its client's rotation, and the
    /// client at the back of the clients' rotation if it had no queued face.
    fn enqueue_face(&mut self, (client, track): QueueKey) {
        let faces = self.faces.entry(client).or_default();
        if faces.is_empty() {
            self.clients.push_back(client);
        }
        faces.push_back(track);
    }

    /// The next crop in fair order: the client at the front of the rotation, its face at the front of its
    /// own rotation; each goes to the back while it still has queued crops.
    fn next_crop(&mut self, may_take: impl Fn(ClientId) -> bool) -> Option<Pending<T>> {
        for _ in 0..self.clients.len() {
            let Some(client) = self.clients.pop_front() else {
                break;
            };
            if !may_take(client) {
                self.clients.push_back(client);
                continue;
            }
            let Some(faces) = self.faces.get_mut(&client) else {
                continue;
            };
            let mut item = None;
            while item.is_none() {
                let Some(track) = faces.pop_front() else {
                    break;
                };
                let key = (client, track);
                let Some(queue) = self.queues.get_mut(&key) else {
                    continue;
                };
                item = queue.pop_front();
                if queue.is_empty() {
                    self.queues.remove(&key);
                } else {
                    faces.push_back(track);
                }
            }
            if faces.is_empty() {
                self.faces.remove(&client);
            } else {
                self.clients.push_back(client);
            }
            if let Some(item) = item {
                self.len -= 1;
                return Some(item);
            }
        }
        None
    }

    fn prune(&mut self) {
        self.queues.retain(|_, q| !q.is_empty());
        let queues = &self.queues;
        for (client, faces) in &mut self.faces {
            faces.retain(|t| queues.contains_key(&(*client, *t)));
        }
        self.faces.retain(|_, f| !f.is_empty());
        let faces = &self.faces;
        self.clients.retain(|c| faces.contains_key(c));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    struct Clock(Instant);

    impl Clock {
        fn at(&self, ms: u64) -> Instant {
            self.0 + MS * u32::try_from(ms).unwrap()
        }
    }

    fn item(clock: &Clock, client: ClientId, frame_id: u64, at_ms: u64, deadline_ms: u64) -> Pending<()> {
        tracked(clock, (client, 0), frame_id, at_ms, deadline_ms)
    }

    fn tracked(clock: &Clock, key: QueueKey, frame_id: u64, at_ms: u64, deadline_ms: u64) -> Pending<()> {
        Pending {
            client: key.0,
            track: key.1,
            frame_id,
            arrived: clock.at(at_ms),
            expires: clock.at(at_ms + deadline_ms),
            payload: (),
        }
    }

    /// `max_wait_ms` 0 = work-conserving.
    fn cfg(max_batch: usize, max_wait_ms: u64, per_client: usize) -> BatcherConfig {
        BatcherConfig {
            max_batch,
            policy: match max_wait_ms {
                0 => BatchPolicy::WorkConserving,
                ms => BatchPolicy::MaxWait(MS * u32::try_from(ms).unwrap()),
            },
            per_client_queue: per_client,
            max_queued: 1000,
        }
    }

    fn drops(b: &mut DynamicBatcher<()>) -> Vec<(ClientId, u64, DropReason)> {
        std::iter::from_fn(|| b.poll_dropped())
            .map(|d| (d.item.client, d.item.frame_id, d.reason))
            .collect()
    }

    fn ids(batch: &Batch<()>) -> Vec<(ClientId, u64)> {
        batch.items.iter().map(|i| (i.client, i.frame_id)).collect()
    }

    #[test]
    fn fires_immediately_when_full() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(3, 4, 1));
        for client in 0..3 {
            b.push(item(&c, client, 1, 0, 100), c.at(0));
        }
        let batch = b.poll_batch(c.at(0)).expect("full batch fires at once");
        assert_eq!(batch.items.len(), 3);
        assert_eq!(batch.formed_at, c.at(0));
        assert!(b.is_empty());
        assert_eq!(b.poll_timeout(), None);
    }

    /// The idle-engine case: one headset's frame goes the moment it arrives, with no batching delay; while
    /// the engine is busy (the driver does not ask), later frames accumulate into the next batch.
    #[test]
    fn work_conserving_sends_at_once_to_an_idle_engine_and_batches_while_busy() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 0, 1));
        b.push(item(&c, 1, 1, 0, 100), c.at(0));
        assert_eq!(b.poll_timeout(), Some(c.at(0)), "due now, not after a wait");
        let first = b
            .poll_batch(c.at(0))
            .expect("an idle engine takes the lone frame at once");
        assert_eq!(ids(&first), vec![(1, 1)]);
        assert_eq!(first.formed_at, c.at(0));
        // The engine is busy with `first` from 0 to 3 ms: three headsets' frames arrive meanwhile.
        for (client, at) in [(1, 1), (2, 1), (3, 2)] {
            b.push(item(&c, client, 2, at, 100), c.at(at));
        }
        let second = b.poll_batch(c.at(3)).expect("engine idle again at 3 ms");
        assert_eq!(ids(&second), vec![(1, 2), (2, 2), (3, 2)]);
        assert!(b.poll_batch(c.at(3)).is_none());
        assert_eq!(b.poll_timeout(), None);
    }

    #[test]
    fn partial_batch_waits_max_wait_then_flushes() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 4, 1));
        b.push(item(&c, 1, 1, 0, 100), c.at(0));
        b.push(item(&c, 2, 1, 1, 100), c.at(1));
        assert!(b.poll_batch(c.at(3)).is_none());
        assert_eq!(
            b.poll_timeout(),
            Some(c.at(4)),
            "flush deadline of the oldest frame"
        );
        let batch = b.poll_batch(c.at(4)).expect("flushes at t0+4ms");
        assert_eq!(ids(&batch), vec![(1, 1), (2, 1)]);
    }

    #[test]
    fn newer_frame_supersedes_queued_one() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 4, 1));
        b.push(item(&c, 7, 1, 0, 100), c.at(0));
        b.push(item(&c, 7, 2, 1, 100), c.at(1));
        assert_eq!(drops(&mut b), vec![(7, 1, DropReason::Superseded)]);
        assert_eq!(b.len(), 1);
        let batch = b.poll_batch(c.at(10)).unwrap();
        assert_eq!(ids(&batch), vec![(7, 2)]);
    }

    #[test]
    fn older_frame_arriving_late_is_superseded_on_arrival() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 4, 2));
        b.push(item(&c, 7, 5, 0, 100), c.at(0));
        b.push(item(&c, 7, 4, 0, 100), c.at(0));
        assert_eq!(drops(&mut b), vec![(7, 4, DropReason::Superseded)]);
        assert_eq!(b.len(), 1);
    }

    #[test]
    fn queue_depth_two_keeps_two_newest() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 4, 2));
        for f in 1..=4 {
            b.push(item(&c, 1, f, 0, 100), c.at(0));
        }
        assert_eq!(
            drops(&mut b),
            vec![(1, 1, DropReason::Superseded), (1, 2, DropReason::Superseded)]
        );
        let batch = b.poll_batch(c.at(4)).unwrap();
        assert_eq!(ids(&batch), vec![(1, 3), (1, 4)]);
    }

    #[test]
    fn expired_frames_never_reach_a_batch() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 10, 1));
        b.push(item(&c, 1, 1, 0, 5), c.at(0));
        b.push(item(&c, 2, 1, 0, 50), c.at(0));
        assert_eq!(
            b.poll_timeout(),
            Some(c.at(5)),
            "earliest deadline comes before the flush"
        );
        b.handle_timeout(c.at(5));
        assert_eq!(drops(&mut b), vec![(1, 1, DropReason::Expired)]);
        let batch = b.poll_batch(c.at(10)).unwrap();
        assert_eq!(ids(&batch), vec![(2, 1)]);
        // Already stale on arrival.
        b.push(item(&c, 3, 1, 0, 5), c.at(6));
        assert_eq!(drops(&mut b), vec![(3, 1, DropReason::Expired)]);
        assert!(b.is_empty());
    }

    #[test]
    fn poll_batch_expires_before_forming() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(2, 4, 1));
        b.push(item(&c, 1, 1, 0, 3), c.at(0));
        b.push(item(&c, 2, 1, 0, 30), c.at(0));
        // Engine was busy; at t=20 the first frame is stale.
        let batch = b.poll_batch(c.at(20)).unwrap();
        assert_eq!(ids(&batch), vec![(2, 1)]);
        assert_eq!(drops(&mut b), vec![(1, 1, DropReason::Expired)]);
    }

    #[test]
    fn round_robin_is_fair_to_light_clients() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(4, 4, 10));
        for f in 1..=10 {
            b.push(item(&c, 1, f, 0, 1000), c.at(0));
        }
        b.push(item(&c, 2, 1, 0, 100), c.at(0));
        b.push(item(&c, 3, 1, 0, 100), c.at(0));
        // Three active clients: one crop each.
        let batch = b.poll_batch(c.at(0)).unwrap();
        assert_eq!(ids(&batch), vec![(1, 1), (2, 1), (3, 1)]);
        // While the light clients are active, the heavy one gets one crop a batch (it cannot hold the
        // engine for a whole batch while they may send again).
        let batch = b.poll_batch(c.at(10)).unwrap();
        assert_eq!(ids(&batch), vec![(1, 2)]);
        // Once they have been quiet for the active window, it fills the batch.
        let later = c.at(10) + ACTIVE_WINDOW + MS;
        let batch = b.poll_batch(later).unwrap();
        assert_eq!(ids(&batch), vec![(1, 3), (1, 4), (1, 5), (1, 6)]);
    }

    #[test]
    fn rotation_continues_across_batches() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(1, 0, 3));
        for client in 1..=3 {
            for f in 1..=3 {
                b.push(item(&c, client, f, 0, 100), c.at(0));
            }
        }
        let order: Vec<ClientId> = std::iter::from_fn(|| b.poll_batch(c.at(0)))
            .map(|batch| batch.items[0].client)
            .collect();
        assert_eq!(order, vec![1, 2, 3, 1, 2, 3, 1, 2, 3]);
    }

    #[test]
    fn global_bound_sheds_new_frames() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(BatcherConfig {
            max_queued: 2,
            ..cfg(8, 4, 1)
        });
        for client in 1..=3 {
            b.push(item(&c, client, 1, 0, 100), c.at(0));
        }
        assert_eq!(drops(&mut b), vec![(3, 1, DropReason::Overloaded)]);
        assert_eq!(b.len(), 2);
        // Superseding within a client does not count against the bound.
        b.push(item(&c, 1, 2, 0, 100), c.at(0));
        assert_eq!(drops(&mut b), vec![(1, 1, DropReason::Superseded)]);
        assert_eq!(b.len(), 2);
    }

    #[test]
    fn drain_answers_everything_with_shutting_down() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 4, 1));
        b.push(item(&c, 1, 1, 0, 100), c.at(0));
        b.push(item(&c, 2, 1, 0, 100), c.at(0));
        b.start_drain();
        b.push(item(&c, 3, 1, 0, 100), c.at(0));
        let mut got = drops(&mut b);
        got.sort_unstable_by_key(|d| d.0);
        assert_eq!(
            got,
            vec![
                (1, 1, DropReason::ShuttingDown),
                (2, 1, DropReason::ShuttingDown),
                (3, 1, DropReason::ShuttingDown)
            ]
        );
        assert!(b.is_empty() && b.is_draining());
        assert!(b.poll_batch(c.at(100)).is_none());
    }

    #[test]
    fn removed_client_is_forgotten() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 4, 2));
        b.push(item(&c, 1, 1, 0, 100), c.at(0));
        b.push(item(&c, 1, 2, 0, 100), c.at(0));
        b.push(item(&c, 2, 1, 0, 100), c.at(0));
        assert_eq!(b.remove_client(1), 2);
        assert_eq!(b.len(), 1);
        let batch = b.poll_batch(c.at(4)).unwrap();
        assert_eq!(ids(&batch), vec![(2, 1)]);
        assert!(drops(&mut b).is_empty());
    }

    fn keys(batch: &Batch<()>) -> Vec<(QueueKey, u64)> {
        batch
            .items
            .iter()
            .map(|i| ((i.client, i.track), i.frame_id))
            .collect()
    }

    /// One headset, three faces, one frame: all three crops batch together, and the next frame's crop of
    /// one face supersedes only that face's queued crop.
    #[test]
    fn faces_of_one_client_batch_together_and_supersede_only_their_own_track() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 0, 1));
        for track in 1..=3 {
            b.push(tracked(&c, (7, track), 10, 0, 100), c.at(0));
        }
        assert!(
            drops(&mut b).is_empty(),
            "same frame id on three tracks: none supersedes another"
        );
        assert_eq!(b.len(), 3);
        // Frame 11 of face 2 arrives before the engine took frame 10.
        b.push(tracked(&c, (7, 2), 11, 1, 100), c.at(1));
        assert_eq!(drops(&mut b), vec![(7, 10, DropReason::Superseded)]);
        // A late crop of frame 10 for face 3 (already queued at 10) is a duplicate of this face, superseded.
        b.push(tracked(&c, (7, 3), 9, 1, 100), c.at(1));
        assert_eq!(drops(&mut b), vec![(7, 9, DropReason::Superseded)]);
        let batch = b.poll_batch(c.at(1)).unwrap();
        let mut got = keys(&batch);
        got.sort_unstable();
        assert_eq!(got, vec![((7, 1), 10), ((7, 2), 11), ((7, 3), 10)]);
    }

    /// Fairness is per client, then per face: a three-face headset gets one slot a batch like a one-face
    /// headset while both are active, its faces take turns, and once the other has nothing queued it is
    /// served alone, one crop a batch (the other is still active).
    #[test]
    fn fairness_is_per_client_then_per_face() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(2, 0, 4));
        for f in 1..=2 {
            for track in 1..=3 {
                b.push(tracked(&c, (1, track), f, 0, 100), c.at(0));
            }
            b.push(tracked(&c, (2, 0), f, 0, 100), c.at(0));
        }
        let served: Vec<QueueKey> = std::iter::from_fn(|| b.poll_batch(c.at(0)))
            .flat_map(|batch| batch.items.into_iter().map(|i| (i.client, i.track)))
            .collect();
        assert_eq!(
            served,
            vec![(1, 1), (2, 0), (1, 2), (2, 0), (1, 3), (1, 1), (1, 2), (1, 3)]
        );
    }

    /// The scenario of issue 30 on made-up instants: an eight-face headset at 30 fps (240 crops/s) beside a
    /// one-face headset at 30 fps, on an engine that aligns 75 crops/s. Per face, the one-face headset got
    /// a ninth of the engine and lost most of its frames; per client it gets what it asks for.
    #[test]
    fn a_client_with_many_faces_does_not_starve_a_one_face_client() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(BatcherConfig {
            max_batch: 8,
            policy: BatchPolicy::WorkConserving,
            per_client_queue: 1,
            max_queued: 1000,
        });
        let per_crop = Duration::from_micros(13_333);
        let (mut busy_until, mut frame) = (c.at(0), 0u64);
        let (mut sent, mut answered) = ([0u64; 3], [0u64; 3]);
        let mut latencies = Vec::new();
        for ms in 0..10_000u64 {
            let now = c.at(ms);
            if ms % 33 == 0 {
                frame += 1;
                for track in 1..=8 {
                    b.push(tracked(&c, (1, track), frame, ms, 100), now);
                }
                b.push(tracked(&c, (2, 0), frame, ms, 100), now);
                sent[1] += 8;
                sent[2] += 1;
            }
            drops(&mut b);
            if now >= busy_until
                && let Some(batch) = b.poll_batch(now)
            {
                busy_until = now + per_crop * u32::try_from(batch.items.len()).unwrap();
                for i in &batch.items {
                    answered[usize::try_from(i.client).unwrap()] += 1;
                    if i.client == 2 {
                        latencies.push(busy_until - i.arrived);
                    }
                }
            }
        }
        let share = |k: usize| answered[k] as f64 / sent[k] as f64;
        latencies.sort_unstable();
        let p99 = latencies[latencies.len() * 99 / 100];
        assert!(share(2) >= 0.95, "one-face client answered {:.3}", share(2));
        // Alone it would wait for nothing but its own crop; beside the heavy client, at most for one other.
        assert!(p99 <= per_crop * 2, "one-face client p99 {p99:?}");
        // The heavy client gets the rest of the engine, not less than its fair part.
        assert!(answered[1] as f64 >= 0.5 * 75.0 * 10.0, "{answered:?}");
    }

    /// Under overload a client cycling through track ids leaves no empty queue behind.
    #[test]
    fn overload_does_not_grow_the_queue_map() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(BatcherConfig {
            max_queued: 2,
            ..cfg(8, 0, 1)
        });
        for track in 0..1000u16 {
            b.push(tracked(&c, (1, track), 1, 0, 100), c.at(0));
        }
        assert_eq!(b.len(), 2);
        assert_eq!(
            b.queues.len(),
            2,
            "one queue per queued crop, none for the shed ones"
        );
        assert_eq!(drops(&mut b).len(), 998);
    }

    #[test]
    fn removing_a_client_forgets_every_track() {
        let c = Clock(Instant::now());
        let mut b = DynamicBatcher::new(cfg(8, 0, 1));
        for track in 1..=3 {
            b.push(tracked(&c, (1, track), 1, 0, 100), c.at(0));
        }
        b.push(tracked(&c, (2, 5), 1, 0, 100), c.at(0));
        assert_eq!(b.remove_client(1), 3);
        assert_eq!(b.len(), 1);
        let batch = b.poll_batch(c.at(0)).unwrap();
        assert_eq!(keys(&batch), vec![((2, 5), 1)]);
        assert!(b.is_empty());
    }

    #[test]
    fn zero_limits_are_raised() {
        let b: DynamicBatcher<()> = DynamicBatcher::new(BatcherConfig {
            max_batch: 0,
            policy: BatchPolicy::WorkConserving,
            per_client_queue: 0,
            max_queued: 0,
        });
        assert_eq!(b.config().max_batch, 1);
        assert_eq!(b.config().per_client_queue, 1);
    }
}
