//! The one send path. Every message, agent -> consumers or consumer -> agent, goes through
//! [`Outbox::send`]: take the topic's next sequence number, wait for receivers to attach where
//! the direction does, loan a sample, fill it, send it, and apply the topic's
//! [`FullQueuePolicy`] when a receiver's queue is full. [`Outbox::send_value`] and
//! [`Outbox::send_slice`] only adapt the two payload shapes iceoryx2 loans.
//!
//! Why the bounded re-send is ours and not iceoryx2's. iceoryx2 0.10 offers a backpressure
//! strategy per publisher (`RetryUntilDelivered`, unbounded, or `DiscardData`) and a
//! backpressure handler (`set_backpressure_handler`, told the retries and the time elapsed) that
//! could bound the retry by time and watch a shutdown flag. Neither is used, because both decide
//! per subscriber inside `send()`: while any one subscriber's queue is full, `send()` waits for
//! that subscriber. The transport's rule is different: a send is done when `required_consumers`
//! receivers have the message, so a second consumer (an observer) that reads slowly does not hold
//! up an agent whose consensus already has it. iceoryx2 cannot express "enough receivers", so
//! publishers use `DiscardData`, `send()` reports how many receivers it reached, and
//! [`Outbox::deliver`] re-sends the same message (same sequence number; receivers drop the
//! duplicates) while a required receiver's queue is full, up to `full_queue_timeout`, watching
//! the shutdown flag and waking the receivers between tries. Publisher history stays off (see
//! the delivery handshake in the module documentation of `transport`), and the subscriber
//! buffer is iceoryx2's own: the topic's queue depth.

use std::cell::Cell;
use std::fmt::Debug;
use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::{EventId, Node, ZeroCopySend};
use iceoryx2::sample_mut::SampleMut;
use iceoryx2::sample_mut_uninit::SampleMutUninit;
use iceoryx2::service::port_factory::PortFactory as _;

use super::error::{loan_error, send_error};
use super::open::{create_publisher, open_topic};
use super::topic::{Service, TopicService};
use super::wake::{notify, wait_for_event};
use super::{FullQueuePolicy, Ipc, TransportConfig, TransportError};

/// Re-send interval while a receiver's queue is full. Receivers do not signal freed space (that
/// would cost a syscall per received message), so an overloaded sender polls at this rate; it is
/// a sleep, not a spin.
const FULL_QUEUE_RETRY: Duration = Duration::from_millis(1);

/// Result of a successful send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SendReport {
    /// Sequence number the sender gave the message (its stamp's `sequence`); a relay, which
    /// forwards the original stamp, counts its own sends here instead.
    pub sequence: u64,
    /// Subscribers the sample was delivered to.
    pub recipients: usize,
    /// Payload plus user-header bytes written to shared memory.
    pub bytes: usize,
}

/// A successful send as the bandwidth accounting sees it.
pub(super) struct Sent {
    pub(super) report: SendReport,
    /// Payload bytes copied from the caller's memory (0 for a message built in place).
    pub(super) copied: usize,
}

/// Who must receive a send, and how the sender treats them.
pub(super) struct Recipients<'a> {
    /// Receivers that must have the message for the send to succeed.
    pub(super) required: usize,
    pub(super) when_absent: WhenAbsent<'a>,
    /// Notified after each send, and before a large one as an early notice.
    pub(super) wake: &'a Notifier<Ipc>,
    pub(super) wake_event: EventId,
    pub(super) config: &'a TransportConfig,
    pub(super) shutdown: &'a AtomicBool,
}

/// What a send does when fewer than the required receivers are attached.
pub(super) enum WhenAbsent<'a> {
    /// Waits for them (agent -> consumers: the delivery handshake, since iceoryx2 silently
    /// drops a sample sent before a subscriber is connected), woken by this listener when a
    /// consumer attaches, up to `delivery_timeout` ([`TransportError::NoConsumer`]).
    Wait(&'a Listener<Ipc>),
    /// Fails at once with [`TransportError::Undelivered`] (consumer -> agent: the consensus
    /// never waits for an agent that is not there).
    Fail,
    /// Waits for them like `Wait`, re-checking every `FULL_QUEUE_RETRY`: for a sender that
    /// cannot own the agent's wake-up listener (a relay standing in for a remote agent, whose
    /// listener belongs to the relay's other direction). Only the first sends wait.
    Poll,
}

/// Sender side of one topic.
pub(super) struct Outbox<T: TopicService> {
    pub(super) name: String,
    publisher: Publisher<Ipc, T::Payload, T::Header>,
    service: Service<T>,
    /// A `Cell`, so that a send borrows the outbox as shared, next to the link's other parts.
    next_sequence: Cell<u64>,
}

impl<T: TopicService> Outbox<T> {
    /// Opens agent `agent_id`'s service of topic `T` and its publisher.
    pub(super) fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<Self, TransportError> {
        let (name, service) = open_topic::<T>(node, config, agent_id)?;
        Self::on(name, service, config, agent_id)
    }

    /// The publisher on an already opened service.
    pub(super) fn on(
        name: String,
        service: Service<T>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<Self, TransportError> {
        let publisher = create_publisher::<T>(&service, &name, config, agent_id)?;
        Ok(Self {
            name,
            publisher,
            service,
            next_sequence: Cell::new(0),
        })
    }

    /// Subscribers attached now.
    pub(super) fn attached(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }

    /// Blocks (event-driven) until `required` subscribers are attached, up to the configured
    /// `delivery_timeout`; [`TransportError::NoConsumer`] when they do not come.
    pub(super) fn await_attached(
        &self,
        required: usize,
        config: &TransportConfig,
        listener: &Listener<Ipc>,
        shutdown: &AtomicBool,
    ) -> Result<(), TransportError> {
        let start = Instant::now();
        loop {
            let attached = self.attached();
            if attached >= required {
                return Ok(());
            }
            let waited = start.elapsed();
            if waited >= config.delivery_timeout {
                return Err(TransportError::NoConsumer {
                    service: self.name.clone(),
                    attached,
                    required,
                    waited,
                });
            }
            let slice = config.wait_slice.min(config.delivery_timeout - waited);
            wait_for_event(listener, slice, shutdown)?;
        }
    }

    /// Sends one message: `send_once(publisher, name, sequence)` loans, fills and sends the
    /// sample and returns the receivers reached; it runs again for every re-send. `bytes` and
    /// `copied` are what the message writes to shared memory, and copies of it from the
    /// caller's memory.
    pub(super) fn send(
        &self,
        to: &Recipients,
        bytes: usize,
        copied: usize,
        mut send_once: impl FnMut(
            &Publisher<Ipc, T::Payload, T::Header>,
            &str,
            u64,
        ) -> Result<usize, TransportError>,
    ) -> Result<Sent, TransportError> {
        let sequence = self.next_sequence.get();
        self.next_sequence.set(sequence + 1);
        let recipients = self.deliver(to, sequence, || {
            send_once(&self.publisher, &self.name, sequence)
        })?;
        Ok(Sent {
            report: SendReport {
                sequence,
                recipients,
                bytes,
            },
            copied,
        })
    }

    /// Sends with `send_once` until `to.required` receivers have the message: waits for them
    /// to attach first where [`WhenAbsent::Wait`], then applies the topic's
    /// [`FullQueuePolicy`]: with `Block`, re-sends (same sequence) while a receiver's queue is
    /// full, up to `full_queue_timeout`.
    fn deliver(
        &self,
        to: &Recipients,
        sequence: u64,
        mut send_once: impl FnMut() -> Result<usize, TransportError>,
    ) -> Result<usize, TransportError> {
        let (required, config) = (to.required, to.config);
        self.await_required(to)?;
        let wake = || notify(to.wake, to.wake_event, "the receivers");
        if T::TOPIC.is_bulk() && !config.poll_before_wait.is_zero() {
            // Early notice: a blocked receiver wakes while the message is being built (its
            // wake-up costs about as much as building a 10k-record patch) and polls until it
            // is sent. Receivers that never poll would only wake twice, hence the condition.
            wake();
        }
        let policy = config.full_queue.of(T::TOPIC);
        let start = Instant::now();
        loop {
            let delivered = send_once()?;
            if delivered >= required {
                wake();
                return Ok(delivered);
            }
            let attached = self.attached();
            // Not a full queue (a `NewestWins` queue never is): a receiver is missing, or is
            // leaving right now.
            if attached < required || policy == FullQueuePolicy::NewestWins {
                match to.when_absent {
                    WhenAbsent::Fail => {
                        return Err(self.undelivered(sequence, delivered, required));
                    }
                    WhenAbsent::Wait(_) | WhenAbsent::Poll if attached < required => {
                        // A receiver left after the handshake: wait for one as before.
                        self.await_required(to)?;
                        continue;
                    }
                    // Leaving right now: the next round tells.
                    WhenAbsent::Wait(_) | WhenAbsent::Poll => {}
                }
            }
            let waited = start.elapsed();
            if waited >= config.full_queue_timeout {
                return Err(match policy {
                    FullQueuePolicy::Block => TransportError::QueueFull {
                        service: self.name.clone(),
                        topic: T::TOPIC,
                        sequence,
                        delivered,
                        required,
                        waited,
                    },
                    FullQueuePolicy::NewestWins => self.undelivered(sequence, delivered, required),
                });
            }
            if to.shutdown.load(Ordering::Relaxed) {
                return Err(TransportError::ShutdownRequested);
            }
            // Wake the receivers again: they may be asleep with a full queue of older data.
            wake();
            std::thread::sleep(FULL_QUEUE_RETRY);
        }
    }

    /// Waits for `to.required` receivers as `to.when_absent` says (nothing to do for `Fail`).
    fn await_required(&self, to: &Recipients) -> Result<(), TransportError> {
        match to.when_absent {
            WhenAbsent::Wait(listener) => {
                self.await_attached(to.required, to.config, listener, to.shutdown)
            }
            WhenAbsent::Poll => self.poll_attached(to.required, to.config, to.shutdown),
            WhenAbsent::Fail => Ok(()),
        }
    }

    /// [`Outbox::await_attached`] without a listener: re-checks every `FULL_QUEUE_RETRY`.
    fn poll_attached(
        &self,
        required: usize,
        config: &TransportConfig,
        shutdown: &AtomicBool,
    ) -> Result<(), TransportError> {
        let start = Instant::now();
        loop {
            let attached = self.attached();
            if attached >= required {
                return Ok(());
            }
            let waited = start.elapsed();
            if waited >= config.delivery_timeout {
                return Err(TransportError::NoConsumer {
                    service: self.name.clone(),
                    attached,
                    required,
                    waited,
                });
            }
            if shutdown.load(Ordering::Relaxed) {
                return Err(TransportError::ShutdownRequested);
            }
            std::thread::sleep(FULL_QUEUE_RETRY);
        }
    }

    fn undelivered(&self, sequence: u64, delivered: usize, required: usize) -> TransportError {
        TransportError::Undelivered {
            service: self.name.clone(),
            sequence,
            delivered,
            required,
        }
    }
}

impl<T: TopicService> Outbox<T>
where
    T::Payload: Sized + ZeroCopySend,
{
    /// Sends the value `message(sequence)`, copied into one sample.
    pub(super) fn send_value(
        &self,
        to: &Recipients,
        message: impl Fn(u64) -> T::Payload,
    ) -> Result<Sent, TransportError> {
        let bytes = size_of::<T::Payload>();
        self.send(to, bytes, bytes, |publisher, name, sequence| {
            let sample = publisher
                .loan_uninit()
                .map_err(|e| loan_error(name, 1, e))?;
            sample
                .write_payload(message(sequence))
                .send()
                .map_err(|e| send_error(name, e))
        })
    }
}

impl<E, T> Outbox<T>
where
    E: Debug + Copy + ZeroCopySend + 'static,
    T: TopicService<Payload = [E]>,
{
    /// Sends a slice of `elements` behind the header `header(sequence)`.
    pub(super) fn send_slice(
        &self,
        to: &Recipients,
        header: impl Fn(u64) -> T::Header,
        mut elements: impl Elements<E>,
    ) -> Result<Sent, TransportError> {
        let len = elements.len();
        let bytes = len * size_of::<E>() + size_of::<T::Header>();
        self.send(
            to,
            bytes,
            elements.copied_bytes(),
            |publisher, name, sequence| {
                let mut sample = publisher
                    .loan_slice_uninit(len)
                    .map_err(|e| loan_error(name, len, e))?;
                *sample.user_header_mut() = header(sequence);
                elements
                    .write(sample)
                    .send()
                    .map_err(|e| send_error(name, e))
            },
        )
    }
}

/// The elements of a slice message: copied from the caller's slice, or built in place in
/// shared memory ([`BuiltInPlace`]). Writing may run more than once (a re-send after a full
/// queue), so a builder must be repeatable.
pub(super) trait Elements<E: Debug + ZeroCopySend> {
    fn len(&self) -> usize;
    /// Bytes copied from the caller's memory.
    fn copied_bytes(&self) -> usize;
    fn write<H: Debug + ZeroCopySend>(
        &mut self,
        sample: SampleMutUninit<Ipc, [MaybeUninit<E>], H>,
    ) -> SampleMut<Ipc, [E], H>;
}

impl<E: Debug + Copy + ZeroCopySend> Elements<E> for &[E] {
    fn len(&self) -> usize {
        <[E]>::len(self)
    }
    fn copied_bytes(&self) -> usize {
        size_of_val(*self)
    }
    fn write<H: Debug + ZeroCopySend>(
        &mut self,
        sample: SampleMutUninit<Ipc, [MaybeUninit<E>], H>,
    ) -> SampleMut<Ipc, [E], H> {
        sample.write_from_slice(self)
    }
}

/// `len` elements, element `i` computed by `build(i)` straight into shared memory.
pub(super) struct BuiltInPlace<F> {
    pub(super) len: usize,
    pub(super) build: F,
}

impl<E: Debug + ZeroCopySend, F: FnMut(usize) -> E> Elements<E> for BuiltInPlace<F> {
    fn len(&self) -> usize {
        self.len
    }
    fn copied_bytes(&self) -> usize {
        0
    }
    fn write<H: Debug + ZeroCopySend>(
        &mut self,
        sample: SampleMutUninit<Ipc, [MaybeUninit<E>], H>,
    ) -> SampleMut<Ipc, [E], H> {
        sample.write_from_fn(&mut self.build)
    }
}
