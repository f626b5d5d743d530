//! What a `.rrd` file holds, read back with rerun's own decoder: its recording ids, and per
//! entity path how many rows carry each component. The swarm tests check recordings with it.

use std::collections::{BTreeMap, BTreeSet};
use std::io::BufReader;
use std::path::Path;

use anyhow::Context;
use re_log_encoding::DecoderApp;
use rerun::external::arrow::array::{Array as _, Float64Array};
use rerun::external::re_log_types::LogMsg;
use rerun::log::Chunk;

/// The component of a `Scalars` time series.
const SCALARS: &str = "Scalars:scalars";

/// The contents of one or more `.rrd` files, summarised.
#[derive(Debug, Clone, Default)]
pub struct RrdSummary {
    /// Recording ids of the recordings (not blueprints) in the files.
    pub recording_ids: BTreeSet<String>,
    /// Entity path -> component (`Archetype:field`, e.g. `Transform3D:translation`) -> rows
    /// that carry it.
    pub entities: BTreeMap<String, BTreeMap<String, usize>>,
    /// Entity path -> component -> most instances in one row (points in a point cloud).
    pub max_instances: BTreeMap<String, BTreeMap<String, usize>>,
    /// Entity path -> largest value of its time series (`Scalars`).
    pub scalar_max: BTreeMap<String, f64>,
}

impl RrdSummary {
    /// Reads `path`; the error names the file.
    pub fn read(path: &Path) -> anyhow::Result<Self> {
        let mut summary = Self::default();
        summary.add(path)?;
        Ok(summary)
    }

    /// Adds the contents of `path`.
    pub fn add(&mut self, path: &Path) -> anyhow::Result<()> {
        let file =
            std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
        for message in DecoderApp::decode_lazy(BufReader::new(file)) {
            let message = message.with_context(|| format!("decoding {}", path.display()))?;
            let LogMsg::ArrowMsg(store, arrow) = message else {
                continue;
            };
            if store.kind() != rerun::StoreKind::Recording {
                continue;
            }
            self.recording_ids.insert(store.recording_id().to_string());
            let chunk = Chunk::from_arrow_msg(&arrow)
                .with_context(|| format!("reading a chunk of {}", path.display()))?;
            // Entity paths print with a leading slash; the live view's paths are written without.
            let path = chunk.entity_path().to_string();
            let entity = path.trim_start_matches('/').to_string();
            for column in chunk.components().values() {
                let component = column.descriptor.component.to_string();
                let list = &column.list_array;
                *self
                    .entities
                    .entry(entity.clone())
                    .or_default()
                    .entry(component.clone())
                    .or_default() += list.len() - list.null_count();
                let most = list.offsets().lengths().max().unwrap_or(0);
                let kept = self
                    .max_instances
                    .entry(entity.clone())
                    .or_default()
                    .entry(component.clone())
                    .or_default();
                *kept = (*kept).max(most);
                if component == SCALARS
                    && let Some(values) = list.values().as_any().downcast_ref::<Float64Array>()
                    && let Some(max) = values.iter().flatten().reduce(f64::max)
                {
                    let kept = self.scalar_max.entry(entity.clone()).or_insert(max);
                    *kept = kept.max(max);
                }
            }
        }
        Ok(())
    }

    /// The most instances `entity` logged in one row of `component` (0 when absent).
    pub fn max_instances(&self, entity: &str, component: &str) -> usize {
        self.max_instances
            .get(entity)
            .and_then(|components| components.get(component))
            .copied()
            .unwrap_or(0)
    }

    /// The largest value of the time series at `entity`.
    pub fn scalar_max(&self, entity: &str) -> Option<f64> {
        self.scalar_max.get(entity).copied()
    }

    /// Rows of `entity` that carry `component` (0 when absent).
    pub fn rows(&self, entity: &str, component: &str) -> usize {
        self.entities
            .get(entity)
            .and_then(|components| components.get(component))
            .copied()
            .unwrap_or(0)
    }
}
