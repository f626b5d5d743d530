//! rosbag2's MCAP storage: records walked one by one from the file's start (so a file cut short
//! is read up to its last whole record, with no need for the summary at its end), chunks
//! decompressed and checksummed by the `mcap` crate. A schema's name is the ROS 2 type; a
//! channel's topic is the topic.

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

use mcap::read::{ChunkReader, parse_record};
use mcap::records::{Record, op};

use super::{BagError, FileScan, Location, Storage, head_of};

/// Opcode byte and 8-byte little-endian length before every record body.
const RECORD_PREFIX: u64 = 9;

/// Topics and types of a file's channels as the records define them.
#[derive(Default)]
struct Channels {
    schema_names: HashMap<u16, String>,
    /// Channel id: (topic, schema id).
    channels: HashMap<u16, (String, u16)>,
}

impl Channels {
    fn define(&mut self, record: &Record) {
        match record {
            Record::Schema { header, .. } => {
                self.schema_names.insert(header.id, header.name.clone());
            }
            Record::Channel(channel) => {
                self.channels
                    .insert(channel.id, (channel.topic.clone(), channel.schema_id));
            }
            _ => {}
        }
    }

    /// (topic, type) of a channel, or why the message cannot be placed.
    fn topic_of(&self, channel_id: u16) -> Result<(String, String), String> {
        let (topic, schema) = self
            .channels
            .get(&channel_id)
            .ok_or_else(|| format!("a message on channel {channel_id}, which no record defines"))?;
        let type_name = self
            .schema_names
            .get(schema)
            .cloned()
            .unwrap_or_else(|| "(no schema)".into());
        Ok((topic.clone(), type_name))
    }
}

/// Scans one MCAP file.
pub(crate) fn scan(path: &Path, number: usize) -> Result<FileScan, BagError> {
    let file = File::open(path).map_err(|e| BagError::io(path, e))?;
    let length = file.metadata().map_err(|e| BagError::io(path, e))?.len();
    let mut magic = [0u8; 8];
    if length < magic.len() as u64
        || file.read_exact_at(&mut magic, 0).is_err()
        || magic != mcap::MAGIC
    {
        return Err(BagError::format(
            path,
            "not an MCAP file (no MCAP magic at its start)",
        ));
    }
    let mut channels = Channels::default();
    let mut messages = Vec::new();
    let mut damage = None;
    let mut offset = mcap::MAGIC.len() as u64;
    loop {
        if offset + RECORD_PREFIX > length {
            damage = Some(format!(
                "the file ends at byte {length} without MCAP's closing records: it was cut short"
            ));
            break;
        }
        let mut prefix = [0u8; RECORD_PREFIX as usize];
        file.read_exact_at(&mut prefix, offset)
            .map_err(|e| BagError::io(path, e))?;
        let opcode = prefix[0];
        let body_length = u64::from_le_bytes(prefix[1..].try_into().expect("8 bytes"));
        let body_offset = offset + RECORD_PREFIX;
        if body_length > length - body_offset {
            damage = Some(format!(
                "a record at byte {offset} runs {} bytes past the end of the file: it was cut short",
                body_length - (length - body_offset)
            ));
            break;
        }
        if opcode == op::DATA_END || opcode == op::FOOTER {
            break;
        }
        let mut body = vec![0u8; body_length as usize];
        file.read_exact_at(&mut body, body_offset)
            .map_err(|e| BagError::io(path, e))?;
        let record = match parse_record(opcode, &body) {
            Ok(record) => record,
            Err(e) => {
                damage = Some(format!("record at byte {offset} does not parse: {e}"));
                break;
            }
        };
        match record {
            Record::Message { header, data } => match channels.topic_of(header.channel_id) {
                Ok((topic, type_name)) => messages.push((
                    topic,
                    type_name,
                    header.log_time,
                    data.len(),
                    head_of(&data),
                    Location::McapRecord {
                        file: number,
                        offset: body_offset,
                        length: body_length,
                    },
                )),
                Err(reason) => {
                    damage = Some(reason);
                    break;
                }
            },
            Record::Chunk { header, data } => {
                let mut ordinal = 0u32;
                let reader = ChunkReader::new(header, &data).map_err(|e| e.to_string());
                let result = reader.and_then(|reader| {
                    for record in reader {
                        let record = record.map_err(|e| e.to_string())?;
                        channels.define(&record);
                        if let Record::Message { header, data } = record {
                            let (topic, type_name) = channels.topic_of(header.channel_id)?;
                            messages.push((
                                topic,
                                type_name,
                                header.log_time,
                                data.len(),
                                head_of(&data),
                                Location::McapChunk {
                                    file: number,
                                    offset: body_offset,
                                    length: body_length,
                                    ordinal,
                                },
                            ));
                            ordinal += 1;
                        }
                    }
                    Ok(())
                });
                if let Err(reason) = result {
                    damage = Some(format!("chunk at byte {offset}: {reason}"));
                    break;
                }
            }
            other => channels.define(&other),
        }
        offset = body_offset + body_length;
    }
    Ok(FileScan {
        storage: Storage::Mcap(file),
        messages,
        damage,
    })
}

/// Reads one message's payload again.
pub(crate) fn read(path: &Path, file: &File, location: Location) -> Result<Vec<u8>, BagError> {
    let (offset, length) = match location {
        Location::McapChunk { offset, length, .. }
        | Location::McapRecord { offset, length, .. } => (offset, length),
        Location::Sqlite { .. } => unreachable!("an sqlite location in an MCAP file"),
    };
    let mut body = vec![0u8; length as usize];
    file.read_exact_at(&mut body, offset)
        .map_err(|e| BagError::io(path, e))?;
    let opcode = match location {
        Location::McapChunk { .. } => op::CHUNK,
        _ => op::MESSAGE,
    };
    let bad = |e: mcap::McapError| BagError::format(path, format!("record at byte {offset}: {e}"));
    match (parse_record(opcode, &body).map_err(bad)?, location) {
        (Record::Message { data, .. }, _) => Ok(data.into_owned()),
        (Record::Chunk { header, data }, Location::McapChunk { ordinal, .. }) => {
            let mut messages = ChunkReader::new(header, &data)
                .map_err(bad)?
                .filter(|r| !matches!(r, Ok(r) if r.opcode() != op::MESSAGE));
            match messages.nth(ordinal as usize) {
                Some(Ok(Record::Message { data, .. })) => Ok(data.into_owned()),
                Some(Err(e)) => Err(bad(e)),
                _ => Err(BagError::format(
                    path,
                    format!("chunk at byte {offset} has no message {ordinal}"),
                )),
            }
        }
        _ => Err(BagError::format(
            path,
            format!("record at byte {offset} is not the message the scan found"),
        )),
    }
}
