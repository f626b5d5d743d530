//! The consensus's durable store: every input the consensus accepts (agents' hellos and
//! goodbyes, complete keyframes with their descriptor and RGB-D image, Gaussian patches, final
//! maps), appended in arrival order to a redb database in the run folder
//! (`OUT/consensus.redb`) and committed before the consensus acts on it. A consensus started on
//! that folder replays the inputs through the same path live messages take
//! ([`crate::process`]), so it rebuilds the same keyframes, pose graph and map (see
//! docs/architecture.md, The consensus store).
//!
//! Why inputs and not results: closures, the pose graph and the merged map are functions of the
//! inputs, and replaying them re-runs the very code that produced them; storing derived state
//! would be a second description of the engine to keep in step with it. The price is that a
//! resume re-aligns the stored candidates (seconds per pair on a CPU).
//!
//! redb commits are atomic and durable (each commit is flushed to disk before it returns): a
//! process killed at any point leaves the store as of its last commit, and a file that was not
//! closed is repaired when opened.
//!
//! The store belongs to one run ([`RunIdentity`]); opening it for another run is refused, never
//! mixed.

mod records;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};

pub use records::{RunIdentity, StoredInput, StoredKeyframe};

/// The store's file name in the run folder.
pub const STORE_FILE: &str = "consensus.redb";

/// Inputs in arrival order: sequence number -> bincode of a [`StoredInput`].
const INPUTS: TableDefinition<u64, &[u8]> = TableDefinition::new("inputs");
/// The run the store belongs to: key `IDENTITY_KEY` -> bincode of a [`RunIdentity`].
const META: TableDefinition<&str, &[u8]> = TableDefinition::new("meta");
const IDENTITY_KEY: &str = "run_identity";

/// How the store was opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Opened {
    /// A new store (none was there, or `--fresh` moved the old one aside).
    New,
    /// The run's own store, with inputs to replay.
    Resumed,
}

/// See the module documentation.
pub struct Store {
    db: Database,
    path: PathBuf,
    next_sequence: u64,
    /// Milliseconds each commit of a keyframe took (serialisation, write and flush).
    keyframe_write_ms: Vec<f64>,
}

impl Store {
    /// Opens the store in `out` for the run `identity`. An existing store of the same run is
    /// resumed: its inputs are returned, oldest first, for replay. One of another run is refused
    /// (naming the file and what differs) unless `fresh`, which moves it aside to
    /// `consensus.redb.replaced` (replacing an older one there) and starts a new store.
    pub fn open(
        out: &Path,
        identity: &RunIdentity,
        fresh: bool,
    ) -> anyhow::Result<(Self, Opened, Vec<StoredInput>)> {
        let path = out.join(STORE_FILE);
        if fresh && path.exists() {
            let aside = out.join(format!("{STORE_FILE}.replaced"));
            std::fs::rename(&path, &aside).with_context(|| {
                format!(
                    "--fresh: moving the previous store {} aside to {}",
                    path.display(),
                    aside.display()
                )
            })?;
            tracing::warn!(
                previous = %aside.display(),
                "--fresh: the previous consensus store was moved aside; starting a new one"
            );
        }
        let existed = path.exists();
        let db = Database::create(&path)
            .with_context(|| format!("opening the consensus store {}", path.display()))?;
        let mut store = Self {
            db,
            path,
            next_sequence: 0,
            keyframe_write_ms: Vec::new(),
        };
        match store.identity()? {
            Some(stored) => {
                let differences = stored.differences(identity);
                if !differences.is_empty() {
                    bail!(
                        "the consensus store {} belongs to another run ({}); start with --fresh \
                         to move it aside and begin a new run, or use another --out folder",
                        store.path.display(),
                        differences.join("; ")
                    );
                }
                let inputs = store.inputs()?;
                store.next_sequence = store.last_sequence()?.map_or(0, |s| s + 1);
                Ok((store, Opened::Resumed, inputs))
            }
            None => {
                if existed {
                    tracing::info!(
                        path = %store.path.display(),
                        "consensus store without a run identity (created and killed before its \
                         first commit): starting it anew"
                    );
                }
                store.write_identity(identity)?;
                Ok((store, Opened::New, Vec::new()))
            }
        }
    }

    /// The store's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends `input` and commits; it is on disk when this returns.
    pub fn append(&mut self, input: &StoredInput) -> anyhow::Result<()> {
        let started = Instant::now();
        let bytes = bincode::serde::encode_to_vec(input, bincode::config::standard())
            .context("encoding a consensus input for the store")?;
        let write = || -> Result<(), redb::Error> {
            let transaction = self.db.begin_write()?;
            transaction
                .open_table(INPUTS)?
                .insert(self.next_sequence, bytes.as_slice())?;
            transaction.commit()?;
            Ok(())
        };
        write().with_context(|| {
            format!(
                "writing to the consensus store {} (input {})",
                self.path.display(),
                self.next_sequence
            )
        })?;
        self.next_sequence += 1;
        if matches!(input, StoredInput::Keyframe(_)) {
            self.keyframe_write_ms
                .push(started.elapsed().as_secs_f64() * 1e3);
        }
        Ok(())
    }

    /// Milliseconds each keyframe's commit took, in order.
    pub fn keyframe_write_ms(&self) -> &[f64] {
        &self.keyframe_write_ms
    }

    fn identity(&self) -> anyhow::Result<Option<RunIdentity>> {
        let read = || -> Result<Option<Vec<u8>>, redb::Error> {
            let transaction = self.db.begin_read()?;
            let table = match transaction.open_table(META) {
                Ok(table) => table,
                Err(redb::TableError::TableDoesNotExist(_)) => return Ok(None),
                Err(error) => return Err(error.into()),
            };
            Ok(table.get(IDENTITY_KEY)?.map(|value| value.value().to_vec()))
        };
        let Some(bytes) = read()
            .with_context(|| format!("reading the consensus store {}", self.path.display()))?
        else {
            return Ok(None);
        };
        let (identity, _) = bincode::serde::decode_from_slice(&bytes, bincode::config::standard())
            .with_context(|| {
                format!(
                    "the consensus store {}: run identity unreadable",
                    self.path.display()
                )
            })?;
        Ok(Some(identity))
    }

    fn write_identity(&self, identity: &RunIdentity) -> anyhow::Result<()> {
        let bytes = bincode::serde::encode_to_vec(identity, bincode::config::standard())?;
        let write = || -> Result<(), redb::Error> {
            let transaction = self.db.begin_write()?;
            transaction
                .open_table(META)?
                .insert(IDENTITY_KEY, bytes.as_slice())?;
            // Created empty, so a resume of a run that stored nothing yet reads no table error.
            transaction.open_table(INPUTS)?;
            transaction.commit()?;
            Ok(())
        };
        write().with_context(|| format!("writing the consensus store {}", self.path.display()))
    }

    /// Every stored input, oldest first.
    fn inputs(&self) -> anyhow::Result<Vec<StoredInput>> {
        let context = || format!("reading the consensus store {}", self.path.display());
        let transaction = self.db.begin_read().with_context(context)?;
        let table = transaction.open_table(INPUTS).with_context(context)?;
        let mut inputs = Vec::new();
        for entry in table.iter().with_context(context)? {
            let (sequence, value) = entry.with_context(context)?;
            let (input, _) =
                bincode::serde::decode_from_slice(value.value(), bincode::config::standard())
                    .with_context(|| {
                        format!(
                            "the consensus store {}: input {} unreadable",
                            self.path.display(),
                            sequence.value()
                        )
                    })?;
            inputs.push(input);
        }
        Ok(inputs)
    }

    fn last_sequence(&self) -> anyhow::Result<Option<u64>> {
        let context = || format!("reading the consensus store {}", self.path.display());
        let transaction = self.db.begin_read().with_context(context)?;
        let table = transaction.open_table(INPUTS).with_context(context)?;
        Ok(table.last().with_context(context)?.map(|(k, _)| k.value()))
    }
}

#[cfg(test)]
mod tests;
