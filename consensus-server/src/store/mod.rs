//! The consensus's durable store, a redb database in the run folder (`OUT/consensus.redb`),
//! holding three things, each committed before the consensus acts on it:
//! - every input the consensus accepts (agents' hellos and goodbyes, complete keyframes with
//!   their descriptor and RGB-D image, Gaussian patches, final maps), in arrival order;
//! - every alignment and map-registration decision ([`Decision`]: the pair, verified or why
//!   not, and a verified closure's transform and uncertainty), in the order they were made;
//! - every correction sent to an agent ([`StoredCorrection`]), per agent in sending order.
//!
//! A consensus started on that folder replays the inputs through the same path live messages
//! take ([`crate::process`]) and hands the decisions to the engine, which applies each one
//! through its own live step once both keyframes are back ([`crate::engine::Engine::apply`]):
//! the pose graph gets the very closures it had, no stored pair is aligned again, and there is
//! one description of the engine, not a second one for the replay. The last correction of each
//! agent is sent again at once (see docs/architecture.md, The consensus store).
//!
//! redb commits are atomic and durable (each commit is flushed to disk before it returns): a
//! process killed at any point leaves the store as of its last commit, and a file that was not
//! closed is repaired when opened.
//!
//! The store belongs to one run ([`RunIdentity`]); opening it for another run is refused, never
//! mixed.

mod records;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, bail};
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition, TableHandle};

pub use records::{RunIdentity, StoredCorrection, StoredInput, StoredKeyframe};

use crate::engine::Decision;

/// The store's file name in the run folder.
pub const STORE_FILE: &str = "consensus.redb";

/// Inputs in arrival order: sequence number -> bincode of a [`StoredInput`].
const INPUTS: TableDefinition<u64, &[u8]> = TableDefinition::new("inputs");
/// The run the store belongs to: key `IDENTITY_KEY` -> bincode of a [`RunIdentity`].
const META: TableDefinition<&str, &[u8]> = TableDefinition::new("meta");
/// Decisions in the order they were made: sequence number -> bincode of a [`Decision`].
const DECISIONS: TableDefinition<u64, &[u8]> = TableDefinition::new("decisions");
/// Corrections sent: (agent id, the agent's sequence number) -> bincode of a
/// [`StoredCorrection`].
const CORRECTIONS: TableDefinition<(u32, u64), &[u8]> = TableDefinition::new("corrections");
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
    /// Shared with the [`DecisionLog`] of the worker thread (redb serialises writers).
    db: Arc<Database>,
    path: PathBuf,
    next_sequence: u64,
    /// Each agent's next correction sequence number.
    next_correction: BTreeMap<u32, u64>,
    /// Milliseconds each commit of a keyframe took (serialisation, write and flush).
    keyframe_write_ms: Vec<f64>,
    /// Fault injection for the chaos soak ([`Store::crash_when_armed`]).
    crash_trigger: Option<PathBuf>,
}

/// Where in storing a keyframe an armed crash kills the process.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CrashPoint {
    /// The keyframe is written in the open transaction, not committed: the store stays as it
    /// was before it.
    BeforeCommit,
    /// The keyframe is committed, and the consensus has not acted on it yet.
    AfterCommit,
}

impl CrashPoint {
    /// The point's name, as the trigger file ([`CRASH_TRIGGER_FILE`]) spells it.
    pub const fn name(self) -> &'static str {
        match self {
            CrashPoint::BeforeCommit => "before_commit",
            CrashPoint::AfterCommit => "after_commit",
        }
    }

    fn parse(text: &str) -> Option<Self> {
        [CrashPoint::BeforeCommit, CrashPoint::AfterCommit]
            .into_iter()
            .find(|point| point.name() == text.trim())
    }
}

/// The file in the output folder that arms a crash (see [`Store::crash_when_armed`]).
pub const CRASH_TRIGGER_FILE: &str = "crash_while_storing";

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
            db: Arc::new(db),
            path,
            next_sequence: 0,
            next_correction: BTreeMap::new(),
            keyframe_write_ms: Vec::new(),
            crash_trigger: None,
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
                store.next_correction = store
                    .last_corrections()?
                    .into_iter()
                    .map(|(agent_id, last)| (agent_id, last.sequence + 1))
                    .collect();
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
        let crash = match input {
            StoredInput::Keyframe(_) => self.armed_crash(),
            _ => None,
        };
        let write = || -> Result<(), redb::Error> {
            let transaction = self.db.begin_write()?;
            transaction
                .open_table(INPUTS)?
                .insert(self.next_sequence, bytes.as_slice())?;
            if crash == Some(CrashPoint::BeforeCommit) {
                crash_now(CrashPoint::BeforeCommit);
            }
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
        if crash == Some(CrashPoint::AfterCommit) {
            crash_now(CrashPoint::AfterCommit);
        }
        self.next_sequence += 1;
        if matches!(input, StoredInput::Keyframe(_)) {
            self.keyframe_write_ms
                .push(started.elapsed().as_secs_f64() * 1e3);
        }
        Ok(())
    }

    /// Fault injection for the chaos soak (`mac-consensus --fault-injection`): from now on,
    /// whenever `OUT/crash_while_storing` exists when a keyframe is stored, the file is removed
    /// and the process kills itself (SIGKILL) at the point it names ([`CrashPoint`]: `before_commit`
    /// or `after_commit`), as a crash at that instant would. Never armed in a normal run.
    pub fn crash_when_armed(&mut self, out: &Path) {
        self.crash_trigger = Some(out.join(CRASH_TRIGGER_FILE));
    }

    /// The crash armed for this keyframe, if any (the trigger file is consumed).
    fn armed_crash(&self) -> Option<CrashPoint> {
        let trigger = self.crash_trigger.as_ref()?;
        let text = std::fs::read_to_string(trigger).ok()?;
        let _ = std::fs::remove_file(trigger);
        let point = CrashPoint::parse(&text);
        if point.is_none() {
            tracing::warn!(file = %trigger.display(), %text, "unknown crash point: not crashing");
        }
        point
    }

    /// Commits the corrections about to be sent (one transaction for all of one solution's),
    /// numbering each agent's from where its stored ones end; returns them numbered.
    pub fn append_corrections(
        &mut self,
        corrections: Vec<StoredCorrection>,
    ) -> anyhow::Result<Vec<StoredCorrection>> {
        let mut numbered = corrections;
        let mut next = self.next_correction.clone();
        let mut encoded = Vec::with_capacity(numbered.len());
        for correction in &mut numbered {
            let sequence = next.entry(correction.agent_id).or_insert(0);
            correction.sequence = *sequence;
            *sequence += 1;
            encoded.push((
                (correction.agent_id, correction.sequence),
                bincode::serde::encode_to_vec(&*correction, bincode::config::standard())
                    .context("encoding a correction for the consensus store")?,
            ));
        }
        let write = || -> Result<(), redb::Error> {
            let transaction = self.db.begin_write()?;
            {
                let mut table = transaction.open_table(CORRECTIONS)?;
                for (key, bytes) in &encoded {
                    table.insert(*key, bytes.as_slice())?;
                }
            }
            transaction.commit()?;
            Ok(())
        };
        write().with_context(|| {
            format!(
                "writing corrections to the consensus store {}",
                self.path.display()
            )
        })?;
        self.next_correction = next;
        Ok(numbered)
    }

    /// The last correction stored for each agent.
    pub fn last_corrections(&self) -> anyhow::Result<BTreeMap<u32, StoredCorrection>> {
        let mut last = BTreeMap::new();
        for correction in read_table::<_, StoredCorrection>(&self.db, &self.path, CORRECTIONS)? {
            last.insert(correction.agent_id, correction);
        }
        Ok(last)
    }

    /// Every stored decision, oldest first.
    pub fn decisions(&self) -> anyhow::Result<Vec<Decision>> {
        read_table(&self.db, &self.path, DECISIONS)
    }

    /// Where the worker thread commits its decisions.
    pub fn decision_log(&self) -> anyhow::Result<DecisionLog> {
        let next_sequence = {
            let context = || format!("reading the consensus store {}", self.path.display());
            let transaction = self.db.begin_read().with_context(context)?;
            match transaction.open_table(DECISIONS) {
                Ok(table) => table
                    .last()
                    .with_context(context)?
                    .map_or(0, |(k, _)| k.value() + 1),
                Err(redb::TableError::TableDoesNotExist(_)) => 0,
                Err(error) => return Err(error).with_context(context),
            }
        };
        Ok(DecisionLog {
            db: Arc::clone(&self.db),
            path: self.path.clone(),
            next_sequence,
        })
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
            transaction.open_table(DECISIONS)?;
            transaction.open_table(CORRECTIONS)?;
            transaction.commit()?;
            Ok(())
        };
        write().with_context(|| format!("writing the consensus store {}", self.path.display()))
    }

    /// Every stored input, oldest first.
    fn inputs(&self) -> anyhow::Result<Vec<StoredInput>> {
        read_table(&self.db, &self.path, INPUTS)
    }

    fn last_sequence(&self) -> anyhow::Result<Option<u64>> {
        let context = || format!("reading the consensus store {}", self.path.display());
        let transaction = self.db.begin_read().with_context(context)?;
        let table = transaction.open_table(INPUTS).with_context(context)?;
        Ok(table.last().with_context(context)?.map(|(k, _)| k.value()))
    }
}

/// The worker thread's end of the store: decisions are committed here before the engine applies
/// them.
pub struct DecisionLog {
    db: Arc<Database>,
    path: PathBuf,
    next_sequence: u64,
}

impl DecisionLog {
    /// Appends `decision` and commits; it is on disk when this returns.
    pub fn append(&mut self, decision: &Decision) -> anyhow::Result<()> {
        let bytes = bincode::serde::encode_to_vec(decision, bincode::config::standard())
            .context("encoding a decision for the consensus store")?;
        let write = || -> Result<(), redb::Error> {
            let transaction = self.db.begin_write()?;
            transaction
                .open_table(DECISIONS)?
                .insert(self.next_sequence, bytes.as_slice())?;
            transaction.commit()?;
            Ok(())
        };
        write().with_context(|| {
            format!(
                "writing to the consensus store {} (decision {})",
                self.path.display(),
                self.next_sequence
            )
        })?;
        self.next_sequence += 1;
        Ok(())
    }
}

/// Makes the store at `path` (a copy of a finished run's, see `mac-consensus --rebuild-from`)
/// the store of a run with the configuration of hash `config_hash`: its recorded identity keeps
/// the run id and agents and takes that hash, so a consensus with the other configuration
/// resumes it instead of refusing it. Returns the identity now recorded.
pub fn adopt_configuration(path: &Path, config_hash: u64) -> anyhow::Result<RunIdentity> {
    let db = Database::open(path)
        .with_context(|| format!("opening the consensus store {}", path.display()))?;
    let store = Store {
        db: Arc::new(db),
        path: path.to_path_buf(),
        next_sequence: 0,
        next_correction: BTreeMap::new(),
        keyframe_write_ms: Vec::new(),
        crash_trigger: None,
    };
    let Some(mut identity) = store.identity()? else {
        bail!(
            "{}: no run recorded in this consensus store",
            path.display()
        );
    };
    identity.config_hash = config_hash;
    store.write_identity(&identity)?;
    Ok(identity)
}

/// The decisions in the store at `path`, oldest first, read without resuming it (for
/// inspection; the store must not be open in a running consensus).
pub fn read_decisions(path: &Path) -> anyhow::Result<Vec<Decision>> {
    let db = Database::open(path)
        .with_context(|| format!("opening the consensus store {}", path.display()))?;
    read_table(&db, path, DECISIONS)
}

/// Every value of `table` in key order, decoded; a table that does not exist (a store written
/// before it was kept) reads as empty.
fn read_table<K, T>(
    db: &Database,
    path: &Path,
    table: TableDefinition<K, &[u8]>,
) -> anyhow::Result<Vec<T>>
where
    K: redb::Key + 'static,
    for<'a> K::SelfType<'a>: std::fmt::Debug,
    T: serde::de::DeserializeOwned,
{
    let context = || format!("reading the consensus store {}", path.display());
    let name = table.name().to_string();
    let transaction = db.begin_read().with_context(context)?;
    let table = match transaction.open_table(table) {
        Ok(table) => table,
        Err(redb::TableError::TableDoesNotExist(_)) => return Ok(Vec::new()),
        Err(error) => return Err(error).with_context(context),
    };
    let mut values = Vec::new();
    for entry in table.iter().with_context(context)? {
        let (key, value) = entry.with_context(context)?;
        let (decoded, _) =
            bincode::serde::decode_from_slice(value.value(), bincode::config::standard())
                .with_context(|| {
                    format!(
                        "the consensus store {}: table {}, entry {:?} unreadable",
                        path.display(),
                        name,
                        key.value()
                    )
                })?;
        values.push(decoded);
    }
    Ok(values)
}

#[cfg(test)]
mod tests;

/// Kills this process at once (SIGKILL: no destructor, no flush), for [`Store::crash_when_armed`].
fn crash_now(point: CrashPoint) -> ! {
    tracing::warn!(
        point = point.name(),
        "fault injection: killing the consensus while storing a keyframe"
    );
    // SAFETY: kill(2) on this very process; it does not return once the signal is delivered.
    unsafe {
        libc::kill(libc::getpid(), libc::SIGKILL);
    }
    unreachable!("SIGKILL is delivered before kill(2) returns to its own process")
}
