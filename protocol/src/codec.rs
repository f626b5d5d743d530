//! The one codec for control messages that hold heap data (strings, vectors): serde + bincode 2
//! behind a small fixed header, so a reader can refuse foreign, truncated, oversized or
//! newer-version bytes with a typed error before bincode sees them.
//!
//! Frame layout (little endian):
//! ```text
//! offset 0  magic          4 bytes  b"MACC"
//! offset 4  format version u16      FORMAT_VERSION
//! offset 6  flags          u16      must be 0 (reserved)
//! offset 8  payload length u32      <= MAX_PAYLOAD_BYTES
//! offset 12 payload        bincode 2 (standard config: varint integers)
//! ```
//! Decoding never panics: every length is checked against the input and the limit, and
//! bincode runs with an allocation limit so a forged length prefix cannot exhaust memory.

use serde::Serialize;
use serde::de::DeserializeOwned;

/// First bytes of every control frame ("MAC Control").
pub const MAGIC: [u8; 4] = *b"MACC";

/// Version of the control-frame format and of the serde types it carries. A reader refuses
/// any other version. 2: `ControlMessage::ResendKeyframe`, frames on the `control` topic.
/// 3: `ControlMessage::ConsensusResumed`. 4: `ControlMessage::MessagesLost`.
pub const FORMAT_VERSION: u16 = 4;

/// Bytes of the fixed header before the payload.
pub const HEADER_LEN: usize = 12;

/// Largest payload accepted or produced: control messages are configs and reports, not maps;
/// bulk data goes through the zero-copy topics.
pub const MAX_PAYLOAD_BYTES: usize = 16 * 1024 * 1024;

const MAGIC_RANGE: std::ops::Range<usize> = 0..4;
const VERSION_RANGE: std::ops::Range<usize> = 4..6;
const FLAGS_RANGE: std::ops::Range<usize> = 6..8;
const LENGTH_RANGE: std::ops::Range<usize> = 8..12;

/// bincode settings: standard (varint, little endian) with the same allocation limit.
fn bincode_config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<MAX_PAYLOAD_BYTES>()
}

/// Why a control message could not be encoded, or a frame decoded. Decoding reports every
/// problem as one of these and never panics.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    /// The input is shorter than the [`HEADER_LEN`]-byte header.
    #[error("control frame truncated: {len} bytes, the header alone needs {HEADER_LEN}")]
    TruncatedHeader {
        /// Bytes in the input.
        len: usize,
    },
    /// The first four bytes are not [`MAGIC`]: this is not a control frame.
    #[error("not a mac-ego3d control frame: magic {found:02x?}, expected {MAGIC:02x?}")]
    BadMagic {
        /// The four bytes found.
        found: [u8; 4],
    },
    /// The frame has another format version than [`FORMAT_VERSION`] (an older or newer build).
    #[error(
        "control frame format version {found} is not supported (this build reads version {FORMAT_VERSION})"
    )]
    UnsupportedVersion {
        /// The version in the header.
        found: u16,
    },
    /// Reserved flag bits are set; this build knows none.
    #[error("control frame has reserved flags {found:#06x} set; this build knows none")]
    UnknownFlags {
        /// The flags in the header.
        found: u16,
    },
    /// The payload exceeds [`MAX_PAYLOAD_BYTES`]: on encode, or as the header declares it.
    #[error("control payload of {len} bytes exceeds the limit of {MAX_PAYLOAD_BYTES} bytes")]
    TooLarge {
        /// Payload bytes, encoded or declared.
        len: usize,
    },
    /// The input ends before the payload length the header declares.
    #[error(
        "control frame truncated: header declares {declared} payload bytes, {available} present"
    )]
    TruncatedPayload {
        /// Payload bytes the header declares.
        declared: usize,
        /// Bytes present after the header.
        available: usize,
    },
    /// Bytes follow the declared payload: the input must be exactly one frame.
    #[error("control frame has {extra} bytes after the declared payload")]
    TrailingFrameBytes {
        /// Bytes after the declared payload.
        extra: usize,
    },
    /// bincode could not decode the payload as the expected type (corrupt bytes, or an
    /// allocation beyond the limit).
    #[error("control payload is malformed: {reason}")]
    Malformed {
        /// bincode's error message.
        reason: String,
    },
    /// The message decoded before the end of the payload.
    #[error("control payload decoded with {unused} bytes left over")]
    TrailingPayloadBytes {
        /// Payload bytes left over.
        unused: usize,
    },
    /// bincode could not encode the message.
    #[error("control message could not be encoded: {reason}")]
    Encode {
        /// bincode's error message.
        reason: String,
    },
}

/// Encodes `message` into a complete frame.
pub fn encode<T: Serialize>(message: &T) -> Result<Vec<u8>, CodecError> {
    let payload = bincode::serde::encode_to_vec(message, bincode_config()).map_err(|e| {
        CodecError::Encode {
            reason: e.to_string(),
        }
    })?;
    if payload.len() > MAX_PAYLOAD_BYTES {
        return Err(CodecError::TooLarge { len: payload.len() });
    }
    let declared =
        u32::try_from(payload.len()).map_err(|_| CodecError::TooLarge { len: payload.len() })?;
    let mut frame = Vec::with_capacity(HEADER_LEN + payload.len());
    frame.extend_from_slice(&MAGIC);
    frame.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    frame.extend_from_slice(&0u16.to_le_bytes());
    frame.extend_from_slice(&declared.to_le_bytes());
    frame.extend_from_slice(&payload);
    Ok(frame)
}

/// Decodes a complete frame produced by [`encode`]; the whole input must be one frame.
pub fn decode<T: DeserializeOwned>(frame: &[u8]) -> Result<T, CodecError> {
    let payload = checked_payload(frame)?;
    let (message, used) = bincode::serde::decode_from_slice::<T, _>(payload, bincode_config())
        .map_err(|e| CodecError::Malformed {
            reason: e.to_string(),
        })?;
    if used != payload.len() {
        return Err(CodecError::TrailingPayloadBytes {
            unused: payload.len() - used,
        });
    }
    Ok(message)
}

/// Validates the header and returns the payload bytes.
fn checked_payload(frame: &[u8]) -> Result<&[u8], CodecError> {
    if frame.len() < HEADER_LEN {
        return Err(CodecError::TruncatedHeader { len: frame.len() });
    }
    let header_field = |range: std::ops::Range<usize>| &frame[range];
    let magic: [u8; 4] = [frame[0], frame[1], frame[2], frame[3]];
    if header_field(MAGIC_RANGE) != MAGIC {
        return Err(CodecError::BadMagic { found: magic });
    }
    let version = u16::from_le_bytes([frame[VERSION_RANGE.start], frame[VERSION_RANGE.start + 1]]);
    if version != FORMAT_VERSION {
        return Err(CodecError::UnsupportedVersion { found: version });
    }
    let flags = u16::from_le_bytes([frame[FLAGS_RANGE.start], frame[FLAGS_RANGE.start + 1]]);
    if flags != 0 {
        return Err(CodecError::UnknownFlags { found: flags });
    }
    let length_bytes = header_field(LENGTH_RANGE);
    let declared = u32::from_le_bytes([
        length_bytes[0],
        length_bytes[1],
        length_bytes[2],
        length_bytes[3],
    ]) as usize;
    if declared > MAX_PAYLOAD_BYTES {
        return Err(CodecError::TooLarge { len: declared });
    }
    let available = frame.len() - HEADER_LEN;
    if declared > available {
        return Err(CodecError::TruncatedPayload {
            declared,
            available,
        });
    }
    if declared < available {
        return Err(CodecError::TrailingFrameBytes {
            extra: available - declared,
        });
    }
    Ok(&frame[HEADER_LEN..])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::ControlMessage;

    fn sample() -> ControlMessage {
        ControlMessage::AgentConfig {
            agent_id: 2,
            config_toml: "[tracking]\nmax_iterations = 64\n".into(),
        }
    }

    #[test]
    fn round_trip() {
        let frame = encode(&sample()).unwrap();
        assert_eq!(&frame[..4], &MAGIC);
        assert_eq!(decode::<ControlMessage>(&frame).unwrap(), sample());
    }

    #[test]
    fn wrong_version_is_a_typed_error() {
        let mut frame = encode(&sample()).unwrap();
        frame[4..6].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
        assert_eq!(
            decode::<ControlMessage>(&frame),
            Err(CodecError::UnsupportedVersion {
                found: FORMAT_VERSION + 1
            })
        );
        let message = decode::<ControlMessage>(&frame).unwrap_err().to_string();
        assert!(
            message.contains(&format!("version {}", FORMAT_VERSION + 1))
                && message.contains(&format!("version {FORMAT_VERSION}")),
            "{message}"
        );
    }

    #[test]
    fn every_truncation_is_refused() {
        let frame = encode(&sample()).unwrap();
        for len in 0..frame.len() {
            let err = decode::<ControlMessage>(&frame[..len]).unwrap_err();
            assert!(
                matches!(
                    err,
                    CodecError::TruncatedHeader { .. } | CodecError::TruncatedPayload { .. }
                ),
                "len {len}: {err}"
            );
        }
    }

    #[test]
    fn oversized_declared_length_is_refused_without_allocating() {
        let mut frame = encode(&sample()).unwrap();
        frame[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            decode::<ControlMessage>(&frame),
            Err(CodecError::TooLarge {
                len: u32::MAX as usize
            })
        );
    }

    #[test]
    fn oversized_message_is_refused_on_encode() {
        let huge = ControlMessage::AgentConfig {
            agent_id: 0,
            config_toml: "x".repeat(MAX_PAYLOAD_BYTES + 1),
        };
        assert!(matches!(
            encode(&huge),
            Err(CodecError::Encode { .. } | CodecError::TooLarge { .. })
        ));
    }

    #[test]
    fn forged_inner_string_length_is_malformed_not_a_panic() {
        // A payload whose varint string length claims far more bytes than exist.
        let mut frame = Vec::from(MAGIC);
        frame.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        frame.extend_from_slice(&0u16.to_le_bytes());
        let payload = [0u8, 2, 0xfc, 0xff, 0xff, 0xff, 0x7f];
        frame.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        frame.extend_from_slice(&payload);
        assert!(matches!(
            decode::<ControlMessage>(&frame),
            Err(CodecError::Malformed { .. })
        ));
    }

    #[test]
    fn trailing_bytes_are_refused() {
        let mut frame = encode(&sample()).unwrap();
        frame.push(0);
        assert_eq!(
            decode::<ControlMessage>(&frame),
            Err(CodecError::TrailingFrameBytes { extra: 1 })
        );
    }
}
