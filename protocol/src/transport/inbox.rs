//! The one receive path: [`Inbox::receive`] takes the next sample of a topic, checks it against
//! its header, and lets the sequence rules ([`super::sequence`]) admit it or drop it as stale or
//! repeated, counting it either way.

use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::Node;
use iceoryx2::sample::Sample;

use super::error::receive_error;
use super::open::{create_subscriber, open_topic};
use super::sequence::{Delivery, ReceiveBook};
use super::topic::{PayloadShape, Service, TopicService};
use super::traffic::TrafficTable;
use super::{Ipc, TransportConfig, TransportError};
use crate::messages::Stamp;

/// A sample admitted by the sequence rules, with how it relates to the ones before it.
pub(super) type Received<T> = (
    Sample<Ipc, <T as TopicService>::Payload, <T as TopicService>::Header>,
    Delivery,
);

/// Receive side of one topic.
pub(super) struct Inbox<T: TopicService> {
    pub(super) name: String,
    subscriber: Subscriber<Ipc, T::Payload, T::Header>,
    // Kept after the port: the port must be dropped before its service.
    _service: Service<T>,
}

impl<T: TopicService> Inbox<T> {
    /// Opens agent `agent_id`'s service of topic `T` and subscribes to it.
    pub(super) fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<Self, TransportError> {
        let (name, service) = open_topic::<T>(node, config, agent_id)?;
        Self::on(name, service, config)
    }

    /// The subscriber on an already opened service.
    pub(super) fn on(
        name: String,
        service: Service<T>,
        config: &TransportConfig,
    ) -> Result<Self, TransportError> {
        let subscriber = create_subscriber::<T>(&service, &name, config)?;
        Ok(Self {
            name,
            subscriber,
            _service: service,
        })
    }

    /// Whether samples are queued (this also maps the memory of the topic's publisher, after
    /// which its samples survive the publisher's exit).
    pub(super) fn has_samples(&self) -> Result<bool, TransportError> {
        self.subscriber
            .has_samples()
            .map_err(|e| receive_error(&self.name, e))
    }

    /// The next admitted sample, without blocking. `check` returns the sample's stamp, or what
    /// is wrong with it ([`TransportError::Malformed`]); the sample is counted under agent
    /// `account_as(stamp)`. Stale and repeated samples are counted and skipped.
    pub(super) fn receive(
        &self,
        book: &mut ReceiveBook,
        traffic: &mut TrafficTable,
        check: impl Fn(&Sample<Ipc, T::Payload, T::Header>) -> Result<Stamp, String>,
        account_as: impl Fn(&Stamp) -> u32,
    ) -> Result<Option<Received<T>>, TransportError> {
        loop {
            let Some(sample) =
                T::Payload::receive(&self.subscriber).map_err(|e| receive_error(&self.name, e))?
            else {
                return Ok(None);
            };
            let stamp = check(&sample).map_err(|reason| TransportError::Malformed {
                service: self.name.clone(),
                reason,
            })?;
            let bytes = size_of_val(T::Payload::payload(&sample)) + size_of::<T::Header>();
            if let Some(delivery) = book.admit(traffic, stamp, T::TOPIC, bytes, account_as(&stamp))
            {
                return Ok(Some((sample, delivery)));
            }
        }
    }
}
