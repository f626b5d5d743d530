//! Per-stage timing of a frame, for benchmarks: [`StageProfiler`] submits and waits for each
//! stage on its own when asked to, and is a no-op otherwise.

use crate::context::{GpuContext, GpuError};

/// Wall-clock milliseconds per forward stage, in pipeline order (see [`crate::gpu::GpuRenderer::render_frame_profiled`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StageTimes(pub Vec<(&'static str, f64)>);

impl StageTimes {
    /// Per-stage medians of several profiled runs (stages matched by position).
    pub fn median_of(runs: &[StageTimes]) -> StageTimes {
        let Some(first) = runs.first() else {
            return StageTimes::default();
        };
        StageTimes(
            first
                .0
                .iter()
                .enumerate()
                .map(|(stage, (name, _))| {
                    let mut values: Vec<f64> = runs
                        .iter()
                        .filter_map(|run| run.0.get(stage).map(|(_, ms)| *ms))
                        .collect();
                    values.sort_by(f64::total_cmp);
                    (*name, values[values.len() / 2])
                })
                .collect(),
        )
    }
}

/// Splits a frame into separately submitted and waited-for stages when profiling; a no-op
/// otherwise (then the stages share command encoders as usual).
pub(crate) struct StageProfiler<'a> {
    times: Option<&'a mut StageTimes>,
    last_mark: std::time::Instant,
}

impl<'a> StageProfiler<'a> {
    pub(crate) fn new(
        context: &GpuContext,
        times: Option<&'a mut StageTimes>,
    ) -> Result<Self, GpuError> {
        if times.is_some() {
            context.wait_idle()?;
        }
        Ok(Self {
            times,
            last_mark: std::time::Instant::now(),
        })
    }

    /// Ends stage `name`: when profiling, submits `encoder`, waits for the device and records
    /// the elapsed time, leaving a fresh encoder in place.
    pub(crate) fn mark(
        &mut self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        name: &'static str,
    ) -> Result<(), GpuError> {
        let Some(times) = self.times.as_deref_mut() else {
            return Ok(());
        };
        let finished = std::mem::replace(
            encoder,
            context.device.create_command_encoder(&Default::default()),
        );
        context.queue.submit([finished.finish()]);
        context.wait_idle()?;
        let now = std::time::Instant::now();
        times
            .0
            .push((name, (now - self.last_mark).as_secs_f64() * 1e3));
        self.last_mark = now;
        Ok(())
    }
}
