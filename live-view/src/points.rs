//! Coloured point sets kept to a bounded count.

/// Points with 8-bit colours.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColouredPoints {
    /// Where the points are, metres, in the frame of the entity they are logged under.
    pub positions: Vec<[f32; 3]>,
    /// Each point's RGB colour (0 to 255), in the order of `positions`.
    pub colours: Vec<[u8; 3]>,
}

impl ColouredPoints {
    /// Every `stride`-th point of `positions` with its colour (`colours` in 0..1, as the
    /// Gaussians keep them), where `stride` keeps at most `max_points`.
    pub fn sampled(positions: &[[f32; 3]], colours: &[[f32; 3]], max_points: usize) -> Self {
        let count = positions.len().min(colours.len());
        let stride = count.div_ceil(max_points.max(1)).max(1);
        let picked = (0..count).step_by(stride);
        Self {
            positions: picked.clone().map(|i| positions[i]).collect(),
            colours: picked.map(|i| colours[i].map(to_byte)).collect(),
        }
    }

    /// How many points it holds.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// True when it holds no point.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// A growing point set kept under `max_points`: when it would pass the bound, every other
/// point is dropped and later additions are thinned as much, so the kept points stay spread
/// over everything added.
#[derive(Debug, Clone)]
pub(crate) struct BoundedPoints {
    points: ColouredPoints,
    max_points: usize,
    /// One point kept out of `stride` of those added.
    stride: usize,
    /// Points added so far (the stride's phase).
    seen: usize,
}

impl BoundedPoints {
    pub fn new(max_points: usize) -> Self {
        Self {
            points: ColouredPoints::default(),
            max_points: max_points.max(2),
            stride: 1,
            seen: 0,
        }
    }

    pub fn extend(&mut self, added: &ColouredPoints) {
        for (position, colour) in added.positions.iter().zip(&added.colours) {
            if self.seen.is_multiple_of(self.stride) {
                self.points.positions.push(*position);
                self.points.colours.push(*colour);
            }
            self.seen += 1;
            if self.points.len() > self.max_points {
                self.halve();
            }
        }
    }

    pub fn points(&self) -> &ColouredPoints {
        &self.points
    }

    fn halve(&mut self) {
        let keep = |i: &usize| i.is_multiple_of(2);
        let positions = std::mem::take(&mut self.points.positions);
        let colours = std::mem::take(&mut self.points.colours);
        self.points.positions = positions
            .into_iter()
            .enumerate()
            .filter(|(i, _)| keep(i))
            .map(|(_, p)| p)
            .collect();
        self.points.colours = colours
            .into_iter()
            .enumerate()
            .filter(|(i, _)| keep(i))
            .map(|(_, c)| c)
            .collect();
        self.stride *= 2;
    }
}

fn to_byte(value: f32) -> u8 {
    (value.clamp(0.0, 1.0) * 255.0).round() as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(n: usize) -> ColouredPoints {
        ColouredPoints {
            positions: (0..n).map(|i| [i as f32, 0.0, 0.0]).collect(),
            colours: vec![[1, 2, 3]; n],
        }
    }

    #[test]
    fn sampling_keeps_at_most_the_bound_and_converts_colours() {
        let positions: Vec<[f32; 3]> = (0..1001).map(|i| [i as f32, 0.0, 0.0]).collect();
        let colours = vec![[0.0, 0.5, 1.0]; 1001];
        let sampled = ColouredPoints::sampled(&positions, &colours, 100);
        assert!(
            sampled.len() <= 100 && sampled.len() >= 50,
            "{}",
            sampled.len()
        );
        assert_eq!(sampled.colours[0], [0, 128, 255]);
        assert_eq!(
            ColouredPoints::sampled(&positions, &colours, 5000).len(),
            1001
        );
    }

    #[test]
    fn bounded_points_stay_under_the_bound_and_spread_over_everything_added() {
        let mut bounded = BoundedPoints::new(1000);
        for _ in 0..50 {
            bounded.extend(&line(100));
        }
        let kept = bounded.points();
        assert!(kept.len() <= 1000 && kept.len() >= 500, "{}", kept.len());
        assert_eq!(kept.positions.len(), kept.colours.len());
        // The last addition is represented, not only the first ones.
        let mut small = BoundedPoints::new(10);
        small.extend(&line(100));
        assert!(small.points().positions.iter().any(|p| p[0] >= 64.0));
    }
}
