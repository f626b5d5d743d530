//! Wake-ups: how a receiver waits for messages without busy waiting, and how senders wake it.
//!
//! Every link has one iceoryx2 event listener. Senders notify it after each send (and before a
//! large one, see [`super::outbox`]); a receive polls its queues for `poll_before_wait` after
//! the link's last activity and then blocks on the listener in slices of `wait_slice`, so a
//! shutdown request is seen promptly ([`receive_within`]). Why the poll: waking a blocked
//! process costs tens of microseconds or more on a loaded or virtualised machine, as much as
//! copying a 10k-Gaussian patch; messages mostly come in bursts, and the poll catches those
//! without sleeping, while an idle receiver blocks at once and burns nothing.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::EventId;

use super::error::wait_error;
use super::{Ipc, TransportConfig, TransportError};
use crate::services::Topic;

/// Event ids on an agent's wake service (consumers -> agent).
pub(super) const WAKE_CORRECTION: usize = 0;
pub(super) const WAKE_CONSUMER_ATTACHED: usize = 1;
pub(super) const WAKE_GOODBYE_SEEN: usize = 2;
pub(super) const WAKE_CONTROL: usize = 3;
pub(super) const AGENT_WAKE_EVENT_IDS: usize = 4;

/// Number of topics, for dense per-agent event ids on the consumers' wake service.
pub(super) const TOPIC_COUNT: usize = Topic::ALL.len();

/// The event id an agent notifies the consumers with after sending on `topic`.
pub(super) fn consumers_wake_event(agent_id: u32, topic: Topic) -> EventId {
    EventId::new(agent_id as usize * TOPIC_COUNT + topic.index())
}

/// Notifies `event` on `notifier`. A failed wake-up only delays the receiver to its next wait
/// slice (the message is queued), so it is logged, not returned.
pub(super) fn notify(notifier: &Notifier<Ipc>, event: EventId, what: &str) {
    if let Err(e) = notifier.notify_with_custom_event_id(event) {
        tracing::warn!(error = ?e, event = event.as_value(), "could not wake {what}");
    }
}

/// Waits on `listener` for at most `timeout`, returning early on any event, with the number of
/// notifications that arrived (0 after a timeout). The event ids themselves are not needed:
/// callers re-check the state they wait for.
pub(super) fn wait_for_event(
    listener: &Listener<Ipc>,
    timeout: Duration,
    shutdown: &AtomicBool,
) -> Result<u64, TransportError> {
    if shutdown.load(Ordering::Relaxed) {
        return Err(TransportError::ShutdownRequested);
    }
    listener.timed_wait(|_| {}, timeout).map_err(wait_error)
}

/// Discards the notifications pending on `listener` without blocking. A receiver that polled
/// its queues has already taken the messages those notifications announced; left pending, they
/// would wake its next wait at once for nothing.
fn discard_pending_events(listener: &Listener<Ipc>) -> Result<(), TransportError> {
    listener.try_wait(|_| {}).map(|_| ()).map_err(wait_error)
}

/// A link's waiting state: its wake-up listener, the shutdown flag, and when it last sent or
/// received a message (receives poll while that is recent).
pub(super) struct Waiting {
    pub(super) listener: Listener<Ipc>,
    pub(super) shutdown: Arc<AtomicBool>,
    pub(super) last_activity: Instant,
    poll_before_wait: Duration,
    wait_slice: Duration,
}

impl Waiting {
    pub(super) fn new(listener: Listener<Ipc>, config: &TransportConfig) -> Self {
        Self {
            listener,
            shutdown: Arc::new(AtomicBool::new(false)),
            last_activity: Instant::now(),
            poll_before_wait: config.poll_before_wait,
            wait_slice: config.wait_slice,
        }
    }

    pub(super) fn mark_activity(&mut self) {
        self.last_activity = Instant::now();
    }
}

/// A link that receives: what [`receive_within`] needs besides the receive itself.
pub(super) trait Receiving {
    fn waiting(&mut self) -> &mut Waiting;
}

/// Calls `try_receive` until it yields a message or `timeout` has passed. While the link's
/// last activity (a message sent or received, or a wake-up) is less than `poll_before_wait`
/// old, it polls, yielding the core between polls; after that it blocks on the link's wake-up
/// event in slices of at most `wait_slice`. A wake-up counts as activity, so a receiver woken
/// by a sender's early notice polls until the message is complete instead of sleeping again.
/// Returns `None` after `timeout`.
pub(super) fn receive_within<L: Receiving, T>(
    link: &mut L,
    timeout: Duration,
    mut try_receive: impl FnMut(&mut L) -> Result<Option<T>, TransportError>,
) -> Result<Option<T>, TransportError> {
    let start = Instant::now();
    loop {
        if let Some(message) = try_receive(link)? {
            link.waiting().mark_activity();
            return Ok(Some(message));
        }
        let waited = start.elapsed();
        if waited >= timeout {
            return Ok(None);
        }
        let waiting = link.waiting();
        if waiting.last_activity.elapsed() < waiting.poll_before_wait {
            if waiting.shutdown.load(Ordering::Relaxed) {
                return Err(TransportError::ShutdownRequested);
            }
            std::thread::yield_now();
            continue;
        }
        // Before sleeping: drop the notifications of messages already taken while polling,
        // then look once more, so that only a notification sent from now on wakes the wait
        // (one sent between the two steps finds its message in the queues).
        discard_pending_events(&waiting.listener)?;
        if let Some(message) = try_receive(link)? {
            link.waiting().mark_activity();
            return Ok(Some(message));
        }
        let waiting = link.waiting();
        let notifications = wait_for_event(
            &waiting.listener,
            waiting.wait_slice.min(timeout - waited),
            &waiting.shutdown,
        )?;
        if notifications > 0 {
            waiting.mark_activity();
        }
    }
}
