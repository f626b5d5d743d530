//! Prefetching frame source: decodes frames on worker threads ahead of the consumer so that PNG/JPEG
//! decoding overlaps tracking and mapping. Frames come out in sequence order, each with its own
//! result (a broken frame is reported and the stream goes on), with bounded memory: at most
//! `workers * queue_per_worker` decoded frames wait at any time.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;

use crossbeam_channel::{Receiver, bounded};

use geometry::files::DatasetError;

use crate::{Dataset, Frame};

/// One item of the stream: the frame's position in the dataset and its decode result.
pub type PrefetchItem = (usize, Result<Frame, DatasetError>);

/// The frames of a dataset in sequence order as an iterator of [`PrefetchItem`]s, decoded ahead on
/// worker threads (see the module documentation). Dropping it stops the workers and waits for each
/// to finish the frame it is decoding.
pub struct Prefetcher {
    /// Worker k decodes positions k, k + W, k + 2W, ...; reading the channels round-robin
    /// restores sequence order without a reorder buffer.
    receivers: Vec<Receiver<PrefetchItem>>,
    next_position: usize,
    len: usize,
    stop: Arc<AtomicBool>,
    workers: Vec<JoinHandle<()>>,
}

impl Prefetcher {
    /// Starts `workers` decoding threads (at least 1), each keeping up to `queue_per_worker` frames
    /// ready (at least 1).
    pub fn new(dataset: Arc<dyn Dataset>, workers: usize, queue_per_worker: usize) -> Self {
        let workers = workers.max(1);
        let len = dataset.len();
        let stop = Arc::new(AtomicBool::new(false));
        let mut receivers = Vec::with_capacity(workers);
        let mut handles = Vec::with_capacity(workers);
        for worker in 0..workers {
            let (tx, rx) = bounded(queue_per_worker.max(1));
            receivers.push(rx);
            let dataset = Arc::clone(&dataset);
            let stop = Arc::clone(&stop);
            let handle = std::thread::Builder::new()
                .name(format!("prefetch-{worker}"))
                .spawn(move || {
                    for position in (worker..len).step_by(workers) {
                        if stop.load(Ordering::Relaxed) {
                            return;
                        }
                        let result = dataset.load(position);
                        if tx.send((position, result)).is_err() {
                            return; // consumer dropped the stream
                        }
                    }
                })
                .expect("spawning a prefetch thread");
            handles.push(handle);
        }
        Self {
            receivers,
            next_position: 0,
            len,
            stop,
            workers: handles,
        }
    }

    /// Number of frames the stream yields in total.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when the stream yields no frames.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl Iterator for Prefetcher {
    type Item = PrefetchItem;

    fn next(&mut self) -> Option<PrefetchItem> {
        if self.next_position >= self.len {
            return None;
        }
        let rx = &self.receivers[self.next_position % self.receivers.len()];
        let item = match rx.recv() {
            Ok(item) => item,
            // A worker only hangs up early if it panicked inside Dataset::load.
            Err(_) => (
                self.next_position,
                Err(DatasetError::Invalid(format!(
                    "frame decoder thread died at position {}",
                    self.next_position
                ))),
            ),
        };
        self.next_position += 1;
        Some(item)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.len - self.next_position;
        (left, Some(left))
    }
}

impl Drop for Prefetcher {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        // Dropping the receivers unblocks workers waiting on a full queue.
        self.receivers.clear();
        for handle in self.workers.drain(..) {
            let _ = handle.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geometry::camera::Intrinsics;
    use geometry::depth::DepthImage;
    use nalgebra::Isometry3;

    /// A dataset whose frames take a little time to "decode" and where frame 3 is broken.
    struct Slow;
    impl Dataset for Slow {
        fn describe(&self) -> String {
            "slow".into()
        }
        fn intrinsics(&self) -> Intrinsics {
            Intrinsics::new(1.0, 1.0, 0.5, 0.5, 2, 2)
        }
        fn len(&self) -> usize {
            10
        }
        fn frame_index(&self, position: usize) -> usize {
            position * 2
        }
        fn timestamp(&self, position: usize) -> f64 {
            position as f64
        }
        fn ground_truth(&self, _: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
            Ok(None)
        }
        fn load(&self, position: usize) -> Result<Frame, DatasetError> {
            std::thread::sleep(std::time::Duration::from_millis((10 - position as u64) * 2));
            if position == 3 {
                return Err(DatasetError::Invalid("broken".into()));
            }
            Ok(Frame {
                index: self.frame_index(position),
                timestamp: position as f64,
                rgb: image::RgbImage::new(2, 2),
                depth: DepthImage::new(2, 2),
                world_from_camera_gt: None,
                ground_truth_error: None,
                colour_offset_s: 0.0,
                intrinsics: self.intrinsics(),
            })
        }
    }

    #[test]
    fn yields_every_frame_in_order_with_errors_in_place() {
        for workers in [1, 3, 16] {
            let items: Vec<_> = Prefetcher::new(Arc::new(Slow), workers, 2).collect();
            assert_eq!(items.len(), 10);
            for (i, (position, result)) in items.iter().enumerate() {
                assert_eq!(*position, i);
                assert_eq!(result.is_err(), i == 3);
                if let Ok(frame) = result {
                    assert_eq!(frame.index, 2 * i);
                }
            }
        }
    }

    #[test]
    fn dropping_early_stops_workers() {
        let mut stream = Prefetcher::new(Arc::new(Slow), 2, 1);
        assert_eq!(stream.next().unwrap().0, 0);
        drop(stream); // must not hang
    }
}
