//! rosbag2 bags read without ROS: a bag folder (metadata.yaml and its storage files), or one
//! storage file, in MCAP ([`mcap`]) or sqlite3 ([`sqlite`]) storage, holding CDR messages.
//!
//! [`Bag::open`] scans the bag once: every message's topic, receive time, size and first bytes
//! (its header, so stamps are known without reading images again), and the whole payload of small
//! messages (calibration, poses, tf). Image payloads are read on demand with [`Bag::read`], from
//! several threads at once. A damaged file (cut short, a chunk whose checksum fails, a database
//! page that will not read) ends the scan at the damage: the messages before it stay usable and
//! [`Bag::damage`] says where the bag broke.

pub mod mcap;
pub mod metadata;
pub mod sqlite;
pub mod writer;

use std::path::{Path, PathBuf};

/// Payloads up to this size are kept whole by the scan (calibration, poses, tf, not images).
pub const SMALL_MESSAGE_BYTES: usize = 8 * 1024;
/// Bytes kept of larger payloads: the encapsulation and a `std_msgs/Header` with a frame name of
/// up to ~200 characters.
pub const HEAD_BYTES: usize = 256;

/// Why a bag cannot be read. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    /// The file system refused: a file or folder missing, unreadable, or not writable.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder concerned.
        path: PathBuf,
        /// What the file system said.
        #[source]
        source: std::io::Error,
    },
    /// A file that is not what a bag holds or is damaged past reading (not MCAP, metadata.yaml
    /// that does not parse, an sqlite3 error, a message that reads back other than the scan
    /// found it), or a bag being written that the MCAP writer refused.
    #[error("{path}: {reason}")]
    Format {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
}

impl BagError {
    pub(crate) fn format(path: &Path, reason: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            reason: reason.into(),
        }
    }
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// One topic of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct Topic {
    /// The topic's full name (`/camera/camera/color/image_raw`).
    pub name: String,
    /// ROS 2 type, `pkg/msg/Type`.
    pub type_name: String,
    /// Messages the scan found on it.
    pub count: usize,
    /// Receive time of its first message, nanoseconds since the Unix epoch.
    pub first_ns: u64,
    /// Receive time of its last message, nanoseconds since the Unix epoch.
    pub last_ns: u64,
}

/// Where a message's payload lives in its storage file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Location {
    /// In an MCAP chunk (the chunk record's body at `offset`, `length` bytes), the `ordinal`-th
    /// message record of the chunk.
    McapChunk {
        file: usize,
        offset: u64,
        length: u64,
        ordinal: u32,
    },
    /// A message record outside chunks (its body).
    McapRecord {
        file: usize,
        offset: u64,
        length: u64,
    },
    /// A row of the messages table.
    Sqlite { file: usize, id: i64 },
}

/// One message as the scan found it.
#[derive(Debug, Clone)]
pub struct MessageRef {
    /// Index into [`Bag::topics`].
    pub topic: usize,
    /// Its position among its topic's messages (0 = first): how errors name it.
    pub index_in_topic: usize,
    /// Receive (log) time, nanoseconds since the epoch.
    pub log_time_ns: u64,
    /// Payload size in bytes.
    pub size: usize,
    /// The whole payload when at most [`SMALL_MESSAGE_BYTES`], else its first [`HEAD_BYTES`].
    pub head: Vec<u8>,
    pub(crate) location: Location,
}

impl MessageRef {
    /// The whole payload, when the scan kept it.
    pub fn payload(&self) -> Option<&[u8]> {
        (self.head.len() == self.size).then_some(&self.head[..])
    }
}

/// Where a damaged bag stopped being readable.
#[derive(Debug, Clone, PartialEq)]
pub struct Damage {
    /// The storage file where reading stopped.
    pub file: PathBuf,
    /// Messages of the whole bag read before the damage.
    pub messages_before: usize,
    /// Where in the file and how it broke (`the file ends at byte N without MCAP's closing
    /// records: it was cut short`).
    pub reason: String,
}

impl std::fmt::Display for Damage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: damaged after {} messages: {}",
            self.file.display(),
            self.messages_before,
            self.reason
        )
    }
}

/// Storage of one file of the bag.
pub(crate) enum Storage {
    Mcap(std::fs::File),
    Sqlite(std::sync::Mutex<rusqlite::Connection>),
}

/// A scanned bag.
pub struct Bag {
    path: PathBuf,
    files: Vec<(PathBuf, Storage)>,
    topics: Vec<Topic>,
    messages: Vec<MessageRef>,
    damage: Option<Damage>,
}

/// What a storage file's scan found: topics are named by (name, type) and merged across files.
pub(crate) struct FileScan {
    pub storage: Storage,
    /// (topic name, type, receive ns, size, head, location) in the file's order.
    pub messages: Vec<(String, String, u64, usize, Vec<u8>, Location)>,
    pub damage: Option<String>,
}

impl Bag {
    /// Opens a bag folder (with or without metadata.yaml) or a single `.mcap` / `.db3` file.
    pub fn open(path: &Path) -> Result<Bag, BagError> {
        let files = metadata::storage_files(path)?;
        let mut bag = Bag {
            path: path.to_path_buf(),
            files: Vec::new(),
            topics: Vec::new(),
            messages: Vec::new(),
            damage: None,
        };
        for (number, file) in files.iter().enumerate() {
            let scan = match file.extension().and_then(|e| e.to_str()) {
                Some("mcap") => mcap::scan(file, number)?,
                Some("db3") => sqlite::scan(file, number)?,
                _ => {
                    return Err(BagError::format(
                        file,
                        "not a rosbag2 storage file (expected .mcap or .db3)",
                    ));
                }
            };
            bag.add(file, scan);
            if bag.damage.is_some() {
                // Later files of a split bag follow the damage in time: keep the bag a prefix.
                break;
            }
        }
        bag.messages.sort_by_key(|m| m.log_time_ns);
        let mut seen = vec![0usize; bag.topics.len()];
        for message in &mut bag.messages {
            message.index_in_topic = seen[message.topic];
            seen[message.topic] += 1;
        }
        Ok(bag)
    }

    fn add(&mut self, file: &Path, scan: FileScan) {
        for (name, type_name, log_time_ns, size, head, location) in scan.messages {
            let topic = match self
                .topics
                .iter()
                .position(|t| t.name == name && t.type_name == type_name)
            {
                Some(topic) => topic,
                None => {
                    self.topics.push(Topic {
                        name,
                        type_name,
                        count: 0,
                        first_ns: log_time_ns,
                        last_ns: log_time_ns,
                    });
                    self.topics.len() - 1
                }
            };
            let entry = &mut self.topics[topic];
            entry.count += 1;
            entry.first_ns = entry.first_ns.min(log_time_ns);
            entry.last_ns = entry.last_ns.max(log_time_ns);
            self.messages.push(MessageRef {
                topic,
                index_in_topic: 0,
                log_time_ns,
                size,
                head,
                location,
            });
        }
        if let Some(reason) = scan.damage {
            self.damage = Some(Damage {
                file: file.to_path_buf(),
                messages_before: self.messages.len(),
                reason,
            });
        }
        self.files.push((file.to_path_buf(), scan.storage));
    }

    /// The path the bag was opened from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The bag's topics, in the order the scan first met them; [`MessageRef::topic`] indexes
    /// this. A name recorded with two types is two topics.
    pub fn topics(&self) -> &[Topic] {
        &self.topics
    }

    /// The topic called `name`, if the bag has it.
    pub fn topic(&self, name: &str) -> Option<usize> {
        self.topics.iter().position(|t| t.name == name)
    }

    /// Every message in receive order.
    pub fn messages(&self) -> &[MessageRef] {
        &self.messages
    }

    /// Where the bag is damaged, when it is.
    pub fn damage(&self) -> Option<&Damage> {
        self.damage.as_ref()
    }

    /// The storage files the bag is made of.
    pub fn files(&self) -> impl Iterator<Item = &Path> {
        self.files.iter().map(|(path, _)| path.as_path())
    }

    /// A message's whole payload.
    pub fn read(&self, message: &MessageRef) -> Result<Vec<u8>, BagError> {
        if let Some(payload) = message.payload() {
            return Ok(payload.to_vec());
        }
        let file = match message.location {
            Location::McapChunk { file, .. }
            | Location::McapRecord { file, .. }
            | Location::Sqlite { file, .. } => file,
        };
        let (path, storage) = &self.files[file];
        let payload = match storage {
            Storage::Mcap(handle) => mcap::read(path, handle, message.location)?,
            Storage::Sqlite(connection) => sqlite::read(path, connection, message.location)?,
        };
        if payload.len() != message.size {
            return Err(BagError::format(
                path,
                format!(
                    "message {} of {} read back as {} bytes, the scan found {}",
                    message.index_in_topic,
                    self.topics[message.topic].name,
                    payload.len(),
                    message.size
                ),
            ));
        }
        Ok(payload)
    }
}

/// Keeps a small payload whole and a large one's head.
pub(crate) fn head_of(payload: &[u8]) -> Vec<u8> {
    if payload.len() <= SMALL_MESSAGE_BYTES {
        payload.to_vec()
    } else {
        payload[..HEAD_BYTES].to_vec()
    }
}
