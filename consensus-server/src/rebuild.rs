//! `mac-consensus --rebuild-from RUN --out NEW`: the end of a finished run built again with
//! another configuration (another merge, another joint refinement), without running its agents
//! again. NEW gets a copy of RUN's store, whose recorded configuration becomes the new one
//! ([`crate::store::adopt_configuration`]), and links to RUN's agent folders (the consensus reads
//! their trajectories; evaluation reads their maps). The consensus then resumes NEW like any
//! restarted consensus: the stored inputs and decisions rebuild the engine (no stored pair is
//! aligned again), every agent's goodbye is among them, so it goes straight to the merged map,
//! the refinement and the outputs. RUN is only read.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

use crate::store::{RunIdentity, STORE_FILE, adopt_configuration};

/// Prepares `out` for a rebuild of the run in `from` with the configuration of hash
/// `config_hash`; returns the run's identity (its run id and agents, to start the consensus with).
pub fn prepare(from: &Path, out: &Path, config_hash: u64) -> anyhow::Result<RunIdentity> {
    let source = from.join(STORE_FILE);
    if !source.is_file() {
        bail!(
            "--rebuild-from {}: no consensus store ({STORE_FILE}) there",
            from.display()
        );
    }
    let from = from
        .canonicalize()
        .with_context(|| format!("--rebuild-from {}", from.display()))?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    if out.canonicalize()? == from {
        bail!("--rebuild-from: --out must be another folder than the run's own");
    }
    let target = out.join(STORE_FILE);
    if target.exists() {
        bail!(
            "{} already holds a consensus store: rebuild into an empty folder",
            target.display()
        );
    }
    std::fs::copy(&source, &target)
        .with_context(|| format!("copying {} to {}", source.display(), target.display()))?;
    for agent in agent_folders(&from)? {
        let name = agent.file_name().expect("a folder entry has a name");
        let link = out.join(name);
        if !link.exists() {
            symlink_dir(&agent, &link)?;
        }
    }
    let identity = adopt_configuration(&target, config_hash)?;
    tracing::info!(
        from = %from.display(),
        out = %out.display(),
        run_id = %identity.run_id,
        "rebuilding the end of a finished run with this configuration"
    );
    Ok(identity)
}

/// RUN/agent_K folders.
fn agent_folders(run: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut folders = Vec::new();
    for entry in std::fs::read_dir(run).with_context(|| format!("listing {}", run.display()))? {
        let entry = entry?;
        let name = entry.file_name();
        let is_agent = name
            .to_str()
            .and_then(|n| n.strip_prefix("agent_"))
            .is_some_and(|k| k.parse::<u32>().is_ok());
        if is_agent && entry.path().is_dir() {
            folders.push(entry.path());
        }
    }
    folders.sort();
    Ok(folders)
}

#[cfg(unix)]
fn symlink_dir(target: &Path, link: &Path) -> anyhow::Result<()> {
    std::os::unix::fs::symlink(target, link)
        .with_context(|| format!("linking {} to {}", link.display(), target.display()))
}

#[cfg(not(unix))]
fn symlink_dir(target: &Path, link: &Path) -> anyhow::Result<()> {
    bail!(
        "--rebuild-from links {} to {}: only on unix",
        link.display(),
        target.display()
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::{Opened, Store, StoredInput};

    #[test]
    fn a_copy_of_the_store_resumes_under_the_new_configuration_and_the_run_is_left_alone() {
        let run = tempfile::tempdir().unwrap();
        let identity = RunIdentity {
            run_id: "run-a".into(),
            config_hash: 1,
            agents: Some(2),
        };
        {
            let (mut store, ..) = Store::open(run.path(), &identity, false).unwrap();
            store.append(&StoredInput::Goodbye { agent_id: 1 }).unwrap();
        }
        std::fs::create_dir(run.path().join("agent_1")).unwrap();
        std::fs::write(run.path().join("agent_1/trajectory.tum"), "# empty\n").unwrap();
        std::fs::create_dir(run.path().join("agent_notes")).unwrap();
        let before = std::fs::read(run.path().join(STORE_FILE)).unwrap();

        let out = tempfile::tempdir().unwrap();
        let new = out.path().join("rebuilt");
        let adopted = prepare(run.path(), &new, 7).unwrap();
        assert_eq!(
            adopted,
            RunIdentity {
                config_hash: 7,
                ..identity.clone()
            }
        );
        let (_, opened, inputs) = Store::open(&new, &adopted, false).unwrap();
        assert_eq!(opened, Opened::Resumed);
        assert!(matches!(inputs[..], [StoredInput::Goodbye { agent_id: 1 }]));
        assert!(
            new.join("agent_1/trajectory.tum").is_file(),
            "agent folders linked"
        );
        assert!(!new.join("agent_notes").exists(), "only agent_K folders");
        assert_eq!(
            std::fs::read(run.path().join(STORE_FILE)).unwrap(),
            before,
            "the run's own store is untouched"
        );

        let again = prepare(run.path(), &new, 7).unwrap_err().to_string();
        assert!(again.contains("already holds a consensus store"), "{again}");
        let itself = prepare(run.path(), run.path(), 7).unwrap_err().to_string();
        assert!(itself.contains("another folder"), "{itself}");
        let empty = tempfile::tempdir().unwrap();
        let none = prepare(empty.path(), &new, 7).unwrap_err().to_string();
        assert!(none.contains("no consensus store"), "{none}");
    }
}
