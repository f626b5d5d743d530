//! The topics as iceoryx2 sees them: each topic's payload and user-header types
//! ([`TopicService`]), so that a port on the wrong types does not compile, and the two payload
//! shapes iceoryx2 serves with separate methods ([`PayloadShape`]: one value or a slice), so
//! that the code around them is written once.

use std::fmt::Debug;

use iceoryx2::port::ReceiveError;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::{AllocationStrategy, IceoryxSend, ZeroCopySend};
use iceoryx2::sample::Sample;
use iceoryx2::service::builder::publish_subscribe::{
    Builder as PubSubBuilder, PublishSubscribeOpenOrCreateError,
};
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubService;
use iceoryx2::service::port_factory::publisher::PortFactoryPublisher;

use super::Ipc;
use crate::messages::{
    ControlHeader, CorrectionHeader, GaussianRecord, KeyframeDescriptor, KeyframeImageHeader,
    KeyframePose, Lifecycle, PatchHeader, RgbdPixel,
};
use crate::services::Topic;

/// One publish-subscribe topic: payload and user-header types.
pub(super) trait TopicService {
    type Payload: PayloadShape + ?Sized + 'static;
    type Header: Debug + ZeroCopySend + Default + 'static;
    const TOPIC: Topic;
}

/// The iceoryx2 service of topic `T`.
pub(super) type Service<T> =
    PubSubService<Ipc, <T as TopicService>::Payload, <T as TopicService>::Header>;

macro_rules! topic_service {
    ($name:ident, $topic:expr, $payload:ty, $header:ty) => {
        pub(super) struct $name;
        impl TopicService for $name {
            type Payload = $payload;
            type Header = $header;
            const TOPIC: Topic = $topic;
        }
    };
}

topic_service!(DescriptorTopic, Topic::Descriptor, KeyframeDescriptor, ());
topic_service!(PatchTopic, Topic::Patch, [GaussianRecord], PatchHeader);
topic_service!(
    KeyframeImageTopic,
    Topic::KeyframeImage,
    [RgbdPixel],
    KeyframeImageHeader
);
topic_service!(
    CorrectionTopic,
    Topic::Correction,
    [KeyframePose],
    CorrectionHeader
);
topic_service!(ControlTopic, Topic::Control, [u8], ControlHeader);
topic_service!(LifecycleTopic, Topic::Lifecycle, Lifecycle, ());

/// What differs between a payload of one value and a slice. The two implementations below read
/// alike, but iceoryx2 declares these methods apart for values and for slices, so the same text
/// calls different methods.
pub(super) trait PayloadShape: Debug + IceoryxSend {
    /// Sizes the publisher's data segment: nothing to do for one value; a slice's starts at
    /// `initial` elements and grows by powers of two, so any size that fits in memory can be
    /// sent (iceoryx2 zeroes a new segment, which holds `max_consumers * (queue depth + held
    /// samples) + 1` samples of the largest slice).
    fn data_segment<H: Debug + ZeroCopySend>(
        publisher: PortFactoryPublisher<'_, Ipc, Self, H>,
        initial: usize,
    ) -> PortFactoryPublisher<'_, Ipc, Self, H>;
    fn open_or_create<H: Debug + ZeroCopySend>(
        builder: PubSubBuilder<Self, H, Ipc>,
    ) -> Result<PubSubService<Ipc, Self, H>, PublishSubscribeOpenOrCreateError>;
    fn receive<H: Debug + ZeroCopySend>(
        subscriber: &Subscriber<Ipc, Self, H>,
    ) -> Result<Option<Sample<Ipc, Self, H>>, ReceiveError>;
    fn payload<H: ZeroCopySend>(sample: &Sample<Ipc, Self, H>) -> &Self;
}

impl<P: Debug + ZeroCopySend> PayloadShape for P {
    fn data_segment<H: Debug + ZeroCopySend>(
        publisher: PortFactoryPublisher<'_, Ipc, Self, H>,
        _initial: usize,
    ) -> PortFactoryPublisher<'_, Ipc, Self, H> {
        publisher
    }
    fn open_or_create<H: Debug + ZeroCopySend>(
        builder: PubSubBuilder<Self, H, Ipc>,
    ) -> Result<PubSubService<Ipc, Self, H>, PublishSubscribeOpenOrCreateError> {
        builder.open_or_create()
    }
    fn receive<H: Debug + ZeroCopySend>(
        subscriber: &Subscriber<Ipc, Self, H>,
    ) -> Result<Option<Sample<Ipc, Self, H>>, ReceiveError> {
        subscriber.receive()
    }
    fn payload<H: ZeroCopySend>(sample: &Sample<Ipc, Self, H>) -> &Self {
        sample.payload()
    }
}

impl<E: Debug + ZeroCopySend> PayloadShape for [E] {
    fn data_segment<H: Debug + ZeroCopySend>(
        publisher: PortFactoryPublisher<'_, Ipc, Self, H>,
        initial: usize,
    ) -> PortFactoryPublisher<'_, Ipc, Self, H> {
        publisher
            .initial_max_slice_len(initial)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
    }
    fn open_or_create<H: Debug + ZeroCopySend>(
        builder: PubSubBuilder<Self, H, Ipc>,
    ) -> Result<PubSubService<Ipc, Self, H>, PublishSubscribeOpenOrCreateError> {
        builder.open_or_create()
    }
    fn receive<H: Debug + ZeroCopySend>(
        subscriber: &Subscriber<Ipc, Self, H>,
    ) -> Result<Option<Sample<Ipc, Self, H>>, ReceiveError> {
        subscriber.receive()
    }
    fn payload<H: ZeroCopySend>(sample: &Sample<Ipc, Self, H>) -> &Self {
        sample.payload()
    }
}
