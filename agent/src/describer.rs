//! The keyframe's global descriptor (docs/method.md, The consensus: selection), computed beside
//! the frame loop instead of in it. AlexNet at 320 px costs tens of milliseconds on a CPU, more
//! under a swarm's load (docs/benchmarks.md): inside the loop it held tracking up for several
//! frames every T_comm, which a live camera turns into dropped frames. One worker thread
//! describes keyframes in the order they come, on a one-thread pool of its own (the network's
//! matrix products would otherwise run on tracking's pool), at the priority it is given.

use std::thread::JoinHandle;

use alexnet::descriptor::GlobalDescriptorExtractor;
use crossbeam_channel::{Receiver, Sender};

use crate::swarm::PublishableKeyframe;

/// A keyframe with its descriptor, or why there is none.
pub struct Described {
    /// The keyframe as it was handed in.
    pub keyframe: PublishableKeyframe,
    /// Its L2-normalised global descriptor (AlexNet GeM features, or a grey thumbnail without
    /// weights), or the extractor's error.
    pub descriptor: anyhow::Result<Vec<f32>>,
}

/// The describing thread: keyframes in, described keyframes out, in order.
pub struct Describer {
    jobs: Option<Sender<PublishableKeyframe>>,
    done: Receiver<Described>,
    /// Keyframes handed in and not yet taken back.
    pending: usize,
    thread: Option<JoinHandle<()>>,
}

impl Describer {
    /// Starts the thread at `niceness` (0: the caller's priority).
    pub fn spawn(extractor: GlobalDescriptorExtractor, niceness: i32) -> Self {
        let (jobs, job_receiver) = crossbeam_channel::unbounded::<PublishableKeyframe>();
        let (done_sender, done) = crossbeam_channel::unbounded();
        let thread = std::thread::Builder::new()
            .name("describer".into())
            .spawn(move || {
                config::process::lower_thread_priority(niceness);
                // Started after the priority is lowered: its thread inherits it.
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(1)
                    .thread_name(|_| "describer-pool".into())
                    .build();
                for keyframe in job_receiver {
                    let describe = || {
                        extractor
                            .describe(&keyframe.rgb)
                            .map_err(anyhow::Error::from)
                    };
                    let descriptor = match &pool {
                        Ok(pool) => pool.install(describe),
                        // Without a pool of its own it still runs off the frame loop.
                        Err(_) => describe(),
                    };
                    if done_sender
                        .send(Described {
                            keyframe,
                            descriptor,
                        })
                        .is_err()
                    {
                        return;
                    }
                }
            })
            .expect("spawning the describing thread");
        Self {
            jobs: Some(jobs),
            done,
            pending: 0,
            thread: Some(thread),
        }
    }

    /// Hands a keyframe in; never blocks. When the thread has died (it panicked: it lives as
    /// long as the job channel) the keyframe is lost, and its id is the error.
    pub fn submit(&mut self, keyframe: PublishableKeyframe) -> Result<(), u64> {
        let keyframe_id = keyframe.keyframe_id;
        let Some(jobs) = &self.jobs else {
            return Err(keyframe_id);
        };
        jobs.send(keyframe).map_err(|_| keyframe_id)?;
        self.pending += 1;
        Ok(())
    }

    /// The keyframes described so far, in order; never blocks.
    pub fn ready(&mut self) -> Vec<Described> {
        let described: Vec<Described> = self.done.try_iter().collect();
        self.pending -= described.len();
        described
    }

    /// Every keyframe handed in, described, in order: waits for the thread. Fewer than
    /// [`Self::pending`] only when the thread died holding the rest.
    pub fn wait_all(&mut self) -> Vec<Described> {
        let mut described = Vec::with_capacity(self.pending);
        while self.pending > described.len() {
            match self.done.recv() {
                Ok(item) => described.push(item),
                // The thread died: what it held is lost.
                Err(_) => break,
            }
        }
        self.pending = 0;
        described
    }

    /// Keyframes handed in and not yet taken back.
    pub fn pending(&self) -> usize {
        self.pending
    }
}

impl Drop for Describer {
    fn drop(&mut self) {
        // Closing the job channel ends the thread's loop.
        self.jobs = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geometry::camera::Intrinsics;
    use geometry::depth::DepthImage;
    use image::RgbImage;
    use nalgebra::Isometry3;
    use splats::GaussianCloud;

    fn keyframe(keyframe_id: u64) -> PublishableKeyframe {
        PublishableKeyframe {
            keyframe_id,
            frame_index: keyframe_id,
            timestamp_s: keyframe_id as f64,
            agent_from_camera: Isometry3::identity(),
            intrinsics: Intrinsics::new(40.0, 40.0, 16.0, 12.0, 32, 24),
            rgb: RgbImage::from_fn(32, 24, |x, y| {
                image::Rgb([(x * 8) as u8, (y * 10 + keyframe_id as u32) as u8, 7])
            }),
            depth: DepthImage {
                width: 32,
                height: 24,
                data: vec![1.5; 32 * 24],
            },
            gaussians: GaussianCloud::default(),
        }
    }

    #[test]
    fn keyframes_come_back_described_in_order_with_the_descriptor_computed_inline() {
        let inline = GlobalDescriptorExtractor::Thumbnail;
        let mut describer = Describer::spawn(GlobalDescriptorExtractor::Thumbnail, 3);
        for keyframe_id in 0..5 {
            assert!(describer.submit(keyframe(keyframe_id)).is_ok());
        }
        assert_eq!(describer.pending(), 5);
        let mut described = describer.ready();
        described.extend(describer.wait_all());
        assert_eq!(describer.pending(), 0);
        let ids: Vec<u64> = described.iter().map(|d| d.keyframe.keyframe_id).collect();
        assert_eq!(ids, vec![0, 1, 2, 3, 4]);
        for item in &described {
            let expected = inline.describe(&item.keyframe.rgb).unwrap();
            assert_eq!(item.descriptor.as_ref().unwrap(), &expected);
        }
        assert!(describer.wait_all().is_empty(), "nothing left to wait for");
    }
}
