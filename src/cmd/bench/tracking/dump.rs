//! What `bench tracking` writes besides its report: the frames' points (`--dump-points`), the
//! frames' images (`--dump-images`), for outside trackers to run on exactly the same input, and
//! every frame's outcome (`--frames-csv`).

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use datasets::Frame;
use nalgebra::Point3;

/// Writes frames' points for `--dump-points`: one raw f32 file per frame plus an index.
pub struct PointDump {
    dir: PathBuf,
    index: std::io::BufWriter<std::fs::File>,
}

impl PointDump {
    const INDEX: &str = "frames.tsv";

    pub fn create(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join(Self::INDEX);
        let mut index = std::io::BufWriter::new(
            std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?,
        );
        writeln!(
            index,
            "# timestamp\tpoints file (x y z little-endian f32, camera frame, m)"
        )
        .with_context(|| format!("writing {}", path.display()))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            index,
        })
    }

    pub fn write(
        &mut self,
        frame_index: usize,
        timestamp: f64,
        points: &[Point3<f32>],
    ) -> anyhow::Result<()> {
        let name = format!("points-{frame_index:06}.f32");
        let path = self.dir.join(&name);
        let bytes: Vec<u8> = points
            .iter()
            .flat_map(|p| [p.x, p.y, p.z])
            .flat_map(f32::to_le_bytes)
            .collect();
        std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
        // The timestamp as the TUM writer prints it, so trajectories match the ground truth.
        writeln!(self.index, "{timestamp:.6}\t{name}")
            .with_context(|| format!("writing {}", self.dir.join(Self::INDEX).display()))
    }

    pub fn finish(mut self) -> anyhow::Result<()> {
        self.index
            .flush()
            .with_context(|| format!("writing {}", self.dir.join(Self::INDEX).display()))
    }
}

/// Writes frames' images for `--dump-images`, as the tracker saw them (undistorted when the
/// dataset is): DIR/rgb-NNNNNN.png, DIR/depth-NNNNNN.png (16-bit, millimetres, 0 = invalid),
/// DIR/intrinsics.json (fx, fy, cx, cy, width, height) and DIR/frames.tsv (timestamp, colour
/// file, depth file per frame, in tracking order).
pub struct ImageDump {
    dir: PathBuf,
    index: std::io::BufWriter<std::fs::File>,
    intrinsics_written: bool,
}

impl ImageDump {
    const INDEX: &str = "frames.tsv";

    pub fn create(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join(Self::INDEX);
        let mut index = std::io::BufWriter::new(
            std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?,
        );
        writeln!(index, "# timestamp\trgb file\tdepth file (u16 mm)")
            .with_context(|| format!("writing {}", path.display()))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            index,
            intrinsics_written: false,
        })
    }

    pub fn write(&mut self, frame: &Frame) -> anyhow::Result<()> {
        if !self.intrinsics_written {
            let k = &frame.intrinsics;
            let path = self.dir.join("intrinsics.json");
            let json = serde_json::json!({
                "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
                "width": k.width, "height": k.height,
            });
            std::fs::write(&path, json.to_string())
                .with_context(|| format!("writing {}", path.display()))?;
            self.intrinsics_written = true;
        }
        let rgb_name = format!("rgb-{:06}.png", frame.index);
        let depth_name = format!("depth-{:06}.png", frame.index);
        let rgb_path = self.dir.join(&rgb_name);
        frame
            .rgb
            .save(&rgb_path)
            .with_context(|| format!("writing {}", rgb_path.display()))?;
        datasets::write_depth_png(&self.dir.join(&depth_name), &frame.depth, 1000.0)?;
        writeln!(
            self.index,
            "{:.6}\t{rgb_name}\t{depth_name}",
            frame.timestamp
        )
        .with_context(|| format!("writing {}", self.dir.join(Self::INDEX).display()))
    }

    pub fn finish(mut self) -> anyhow::Result<()> {
        self.index
            .flush()
            .with_context(|| format!("writing {}", self.dir.join(Self::INDEX).display()))
    }
}
