//! A relayed message as bytes: the topic's header (or its one value) followed by its payload
//! elements, exactly as laid out in shared memory. Every wire type is `bytemuck::Pod`, so the
//! bytes are read back without unsafe code and a short or ragged buffer is an error naming the
//! service. Both ends must share byte order (all supported hosts are little-endian; a
//! big-endian build is refused at compile time below).

use std::fmt::Debug;

use bytemuck::Pod;
use iceoryx2::prelude::ZeroCopySend;

use super::super::TransportError;
use super::super::outbox::BuiltInPlace;
use crate::messages::Stamp;
use crate::services::Topic;

#[cfg(target_endian = "big")]
compile_error!("the relay carries shared-memory layouts as bytes: little-endian hosts only");

/// One message on its way between hosts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RelayedMessage {
    /// The agent the message comes from (agent -> consumers topics) or goes to (corrections,
    /// control).
    pub agent_id: u32,
    /// The topic it was published on.
    pub topic: Topic,
    /// The stamp the original sender gave it; it crosses unchanged.
    pub stamp: Stamp,
    /// Header (or value) bytes, then payload element bytes.
    pub bytes: Vec<u8>,
}

impl RelayedMessage {
    /// A message as it arrives from the network: `bytes` for agent `agent_id`'s `topic`. Every
    /// header (and one-value message) starts with its [`Stamp`], read from there.
    pub fn from_network(
        agent_id: u32,
        topic: Topic,
        bytes: Vec<u8>,
    ) -> Result<Self, TransportError> {
        let Some(stamp_bytes) = bytes.get(..size_of::<Stamp>()) else {
            return Err(malformed(
                topic.name(),
                format!(
                    "relayed message of {} bytes for agent {agent_id} is shorter than a stamp",
                    bytes.len()
                ),
            ));
        };
        Ok(Self {
            agent_id,
            topic,
            stamp: bytemuck::pod_read_unaligned(stamp_bytes),
            bytes,
        })
    }
}

/// Bytes of a one-value message.
pub(super) fn value_bytes<P: Pod>(value: &P) -> Vec<u8> {
    bytemuck::bytes_of(value).to_vec()
}

/// Bytes of a header and its slice.
pub(super) fn slice_bytes<H: Pod, E: Pod>(header: &H, elements: &[E]) -> Vec<u8> {
    let header = bytemuck::bytes_of(header);
    let elements: &[u8] = bytemuck::cast_slice(elements);
    let mut bytes = Vec::with_capacity(header.len() + elements.len());
    bytes.extend_from_slice(header);
    bytes.extend_from_slice(elements);
    bytes
}

fn malformed(service: &str, reason: String) -> TransportError {
    TransportError::Malformed {
        service: service.to_string(),
        reason,
    }
}

/// Reads a one-value message.
pub(super) fn read_value<P: Pod>(service: &str, bytes: &[u8]) -> Result<P, TransportError> {
    if bytes.len() != size_of::<P>() {
        return Err(malformed(
            service,
            format!(
                "relayed message of {} bytes, expected {}",
                bytes.len(),
                size_of::<P>()
            ),
        ));
    }
    Ok(bytemuck::pod_read_unaligned(bytes))
}

/// Reads a header and returns it with a builder that writes the elements straight into a
/// loaned shared-memory slice (one copy, from the received buffer; the buffer need not be
/// aligned).
pub(super) fn read_slice<'a, H: Pod, E: Pod + Debug + ZeroCopySend>(
    service: &str,
    bytes: &'a [u8],
) -> Result<(H, BuiltInPlace<impl FnMut(usize) -> E + 'a>), TransportError> {
    let Some((header, elements)) = bytes.split_at_checked(size_of::<H>()) else {
        return Err(malformed(
            service,
            format!(
                "relayed message of {} bytes is shorter than its {}-byte header",
                bytes.len(),
                size_of::<H>()
            ),
        ));
    };
    let element_size = size_of::<E>();
    if elements.len() % element_size != 0 {
        return Err(malformed(
            service,
            format!(
                "relayed payload of {} bytes is not a whole number of {element_size}-byte elements",
                elements.len()
            ),
        ));
    }
    let len = elements.len() / element_size;
    let build = move |i: usize| {
        bytemuck::pod_read_unaligned(&elements[i * element_size..(i + 1) * element_size])
    };
    Ok((
        bytemuck::pod_read_unaligned(header),
        BuiltInPlace { len, build },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::{GaussianRecord, PatchHeader};
    use crate::transport::outbox::Elements;

    #[test]
    fn slice_bytes_read_back_at_any_alignment() {
        let header = PatchHeader {
            keyframe_id: 7,
            count: 3,
            ..PatchHeader::default()
        };
        let records: Vec<GaussianRecord> = (0..3)
            .map(|i| GaussianRecord {
                opacity_logit: i as f32,
                ..GaussianRecord::default()
            })
            .collect();
        let bytes = slice_bytes(&header, &records);
        // One byte of offset: the received buffer is not aligned for f32/u64.
        let mut shifted = vec![0u8];
        shifted.extend_from_slice(&bytes);
        let (read_header, mut build) =
            read_slice::<PatchHeader, GaussianRecord>("test", &shifted[1..]).unwrap();
        assert_eq!(read_header, header);
        assert_eq!(build.len(), 3);
        let read: Vec<GaussianRecord> = (0..3).map(&mut build.build).collect();
        assert_eq!(read, records);
    }

    #[test]
    fn the_stamp_is_read_from_the_front_of_every_message() {
        let stamp = Stamp {
            agent_id: 3,
            reserved: 0,
            epoch: 11,
            sequence: 5,
        };
        let header = PatchHeader {
            stamp,
            ..PatchHeader::default()
        };
        let bytes = slice_bytes(&header, &[GaussianRecord::default()]);
        let message = RelayedMessage::from_network(3, Topic::Patch, bytes).unwrap();
        assert_eq!(message.stamp, stamp);
        assert!(RelayedMessage::from_network(3, Topic::Patch, vec![0; 4]).is_err());
    }

    #[test]
    fn ragged_or_short_bytes_are_refused_by_name() {
        let bytes = slice_bytes(&PatchHeader::default(), &[GaussianRecord::default()]);
        let ragged = &bytes[..bytes.len() - 1];
        let err = read_slice::<PatchHeader, GaussianRecord>("mac/agent/0/patch", ragged)
            .err()
            .unwrap();
        assert!(err.to_string().contains("mac/agent/0/patch"), "{err}");
        assert!(read_slice::<PatchHeader, GaussianRecord>("x", &bytes[..8]).is_err());
        assert!(read_value::<Stamp>("x", &bytes).is_err());
    }
}
