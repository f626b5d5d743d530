//! Property test of the control-message codec: many seeded random inputs (pure noise, mutated
//! valid frames, truncations, forged lengths) must each decode to a message or a typed error,
//! never panic; random valid messages must round-trip exactly.

use protocol::codec::{
    CodecError, FORMAT_VERSION, HEADER_LEN, MAGIC, MAX_PAYLOAD_BYTES, decode, encode,
};
use protocol::messages::ControlMessage;

/// Iterations per property; a few seconds in total at test optimisation.
const CASES: usize = 20_000;
/// Largest random buffer, bytes.
const MAX_NOISE_LEN: usize = 512;
/// Longest random string inside a generated message.
const MAX_TEXT_LEN: usize = 300;

/// xorshift64*: deterministic, dependency-free randomness (seeded per property).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    fn bytes(&mut self, len: usize) -> Vec<u8> {
        (0..len).map(|_| self.next() as u8).collect()
    }

    fn text(&mut self) -> String {
        let len = self.below(MAX_TEXT_LEN);
        // Mix ASCII with multi-byte characters so UTF-8 boundaries are exercised.
        (0..len)
            .map(|_| {
                if self.below(8) == 0 {
                    'é'
                } else {
                    (b' ' + self.below(94) as u8) as char
                }
            })
            .collect()
    }

    fn message(&mut self) -> ControlMessage {
        if self.below(2) == 0 {
            ControlMessage::AgentConfig {
                agent_id: self.next() as u32,
                config_toml: self.text(),
            }
        } else {
            ControlMessage::Shutdown {
                reason: self.text(),
            }
        }
    }
}

#[test]
fn random_messages_round_trip() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for case in 0..CASES {
        let message = rng.message();
        let frame = encode(&message).expect("encode");
        assert_eq!(
            decode::<ControlMessage>(&frame).expect("decode"),
            message,
            "case {case}"
        );
    }
}

#[test]
fn pure_noise_is_refused_without_panic() {
    let mut rng = Rng(0x0123_4567_89ab_cdef);
    for _ in 0..CASES {
        let len = rng.below(MAX_NOISE_LEN);
        let noise = rng.bytes(len);
        // Noise almost never starts with the magic; when it does it still must not panic.
        if let Ok(message) = decode::<ControlMessage>(&noise) {
            assert_eq!(
                &noise[..4],
                &MAGIC,
                "only a frame with the magic can decode: {message:?}"
            );
        }
    }
}

#[test]
fn noise_behind_a_valid_header_is_refused_or_decoded_without_panic() {
    let mut rng = Rng(0xdead_beef_cafe_f00d);
    let mut malformed = 0;
    for _ in 0..CASES {
        let len = rng.below(MAX_NOISE_LEN);
        let payload = rng.bytes(len);
        let mut frame = Vec::from(MAGIC);
        frame.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        frame.extend_from_slice(&0u16.to_le_bytes());
        frame.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        frame.extend_from_slice(&payload);
        match decode::<ControlMessage>(&frame) {
            Ok(_) => {}
            Err(CodecError::Malformed { .. } | CodecError::TrailingPayloadBytes { .. }) => {
                malformed += 1
            }
            Err(other) => panic!("header is valid, so only payload errors are expected: {other}"),
        }
    }
    assert!(
        malformed > CASES / 2,
        "most noise payloads must be refused ({malformed} of {CASES})"
    );
}

#[test]
fn mutated_and_truncated_frames_never_panic() {
    let mut rng = Rng(0x5151_7e57_0000_0001);
    for _ in 0..CASES {
        let mut frame = encode(&rng.message()).expect("encode");
        match rng.below(4) {
            0 => {
                // Flip random bits anywhere, header included.
                for _ in 0..=rng.below(4) {
                    let at = rng.below(frame.len());
                    frame[at] ^= 1 << rng.below(8);
                }
            }
            1 => frame.truncate(rng.below(frame.len())),
            2 => {
                // Forge the declared length.
                let forged = rng.next() as u32;
                frame[8..HEADER_LEN].copy_from_slice(&forged.to_le_bytes());
                if forged as usize > MAX_PAYLOAD_BYTES {
                    assert!(matches!(
                        decode::<ControlMessage>(&frame),
                        Err(CodecError::TooLarge { .. })
                    ));
                }
            }
            _ => {
                let len = 1 + rng.below(16);
                let extra = rng.bytes(len);
                frame.extend_from_slice(&extra);
                assert!(matches!(
                    decode::<ControlMessage>(&frame),
                    Err(CodecError::TrailingFrameBytes { .. })
                ));
            }
        }
        let _ = decode::<ControlMessage>(&frame);
    }
}
