//! What the room holds and where: the random materials and the furniture placement, drawn from
//! the scene's RNG stream for a seed.

use std::f64::consts::PI;

use nalgebra::Vector3;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;

use super::scene::{ROOM_SURFACES, Scene};
use super::shapes::{Primitive, ROOM_MAX, Shape, from_yawed};
use super::texture::{Material, Pattern, Rgb, hsv_to_rgb};
use super::{SCENE_STREAM, stream_rng, symmetric};

fn random_colour(rng: &mut ChaCha8Rng, saturation: (f64, f64), value: (f64, f64)) -> Rgb {
    hsv_to_rgb(
        rng.random_range(0.0..1.0),
        rng.random_range(saturation.0..=saturation.1),
        rng.random_range(value.0..=value.1),
    )
}

fn random_material(rng: &mut ChaCha8Rng, pattern: Pattern, value_range: (f64, f64)) -> Material {
    let primary = random_colour(rng, (0.15, 0.7), value_range);
    // The second colour differs in hue and clearly in brightness, so patterns have contrast in
    // grey-level too (trackers often work on intensity).
    let hsv_hue_shift = rng.random_range(0.08..0.5);
    let secondary_value = if rng.random_bool(0.5) {
        value_range.0 * 0.45
    } else {
        (value_range.1 * 1.15).min(1.0)
    };
    let base_hue = rng.random_range(0.0..1.0);
    let secondary = hsv_to_rgb(
        base_hue + hsv_hue_shift,
        rng.random_range(0.2..0.8),
        secondary_value,
    );
    Material {
        pattern,
        primary,
        secondary,
        noise_seed: rng.random(),
        noise_frequency: rng.random_range(1.5..3.5),
        detail_strength: rng.random_range(0.18..0.32),
        cell_tint: rng.random_range(0.08..0.2),
    }
}

fn random_object_pattern(rng: &mut ChaCha8Rng) -> Pattern {
    match rng.random_range(0..4u32) {
        0 => Pattern::Marble,
        1 => Pattern::Checker {
            period: rng.random_range(0.08..0.2),
        },
        2 => {
            let angle: f64 = rng.random_range(0.0..PI);
            Pattern::Stripes {
                period: rng.random_range(0.06..0.16),
                cos_angle: angle.cos(),
                sin_angle: angle.sin(),
            }
        }
        _ => Pattern::Tiles {
            period: rng.random_range(0.06..0.15),
            grout_half_width: 0.005,
        },
    }
}

/// Builds the room: materials and objects, every random choice drawn from one RNG stream in a
/// fixed order. The order is part of the output (drawing one number earlier or later changes
/// every seed's scene), so each step below keeps the draws of the code it came from.
struct SceneBuilder {
    pub(super) rng: ChaCha8Rng,
    pub(super) primitives: Vec<Primitive>,
    pub(super) materials: Vec<Material>,
}

impl Scene {
    pub(super) fn generate(seed: u64) -> Self {
        let mut builder = SceneBuilder {
            rng: stream_rng(seed, SCENE_STREAM),
            primitives: Vec::new(),
            materials: Vec::new(),
        };
        let room_materials = builder.room_shell();
        builder.table_with_objects();
        let bench_y = builder.furniture_along_walls();
        builder.posters(bench_y);
        Self {
            room_materials,
            primitives: builder.primitives,
            materials: builder.materials,
        }
    }
}

/// An upright box turned by `yaw` about the vertical.
fn cuboid(center: Vector3<f64>, half_size: Vector3<f64>, yaw: f64) -> Shape {
    Shape::Cuboid {
        center,
        half_size,
        cos_yaw: yaw.cos(),
        sin_yaw: yaw.sin(),
    }
}

impl SceneBuilder {
    fn add_material(&mut self, material: Material) -> usize {
        self.materials.push(material);
        self.materials.len() - 1
    }

    /// Adds an object with a material of a random pattern (drawn after the shape's own numbers).
    fn add(&mut self, shape: Shape) {
        let pattern = random_object_pattern(&mut self.rng);
        let material = random_material(&mut self.rng, pattern, (0.35, 0.9));
        let material = self.add_material(material);
        self.primitives.push(Primitive::new(shape, material));
    }

    fn random_room_material(&mut self, pattern: Pattern, value_range: (f64, f64)) -> usize {
        let material = random_material(&mut self.rng, pattern, value_range);
        self.add_material(material)
    }

    /// Room shell: each wall a different kind of pattern, floor planks, ceiling panels. Returns
    /// the materials in the order of [`Scene::room_materials`].
    fn room_shell(&mut self) -> [usize; ROOM_SURFACES] {
        let wall_value = (0.55, 0.9);
        let stripe_angle: f64 = PI / 2.0 + symmetric(&mut self.rng, 0.05);
        let west = self.random_room_material(Pattern::Marble, wall_value);
        let east = self.random_room_material(
            Pattern::Stripes {
                period: 0.21,
                cos_angle: stripe_angle.cos(),
                sin_angle: stripe_angle.sin(),
            },
            wall_value,
        );
        let south = self.random_room_material(Pattern::Checker { period: 0.5 }, wall_value);
        let north = self.random_room_material(
            Pattern::Tiles {
                period: 0.3,
                grout_half_width: 0.008,
            },
            wall_value,
        );
        let floor = self.random_room_material(
            Pattern::Planks {
                width: 0.16,
                length: 1.1,
            },
            (0.45, 0.75),
        );
        let ceiling = self.random_room_material(
            Pattern::Tiles {
                period: 0.6,
                grout_half_width: 0.012,
            },
            (0.7, 0.95),
        );
        [west, east, south, north, floor, ceiling]
    }

    /// Table in the middle of the room, with a box, a ball and a vase on it.
    fn table_with_objects(&mut self) {
        let rng = &mut self.rng;
        let table_center = Vector3::new(symmetric(rng, 0.15), symmetric(rng, 0.1), 0.0);
        let table_yaw = symmetric(rng, 0.25);
        let (top_half, top_height, top_thickness) = (
            Vector3::new(0.6, 0.4, 0.02),
            rng.random_range(0.72..0.78),
            0.04,
        );
        let on_table = |x: f64, y: f64, z: f64| {
            table_center
                + from_yawed(&Vector3::new(x, y, 0.0), table_yaw.cos(), table_yaw.sin())
                + Vector3::new(0.0, 0.0, z)
        };
        self.add(cuboid(
            on_table(0.0, 0.0, top_height - top_half.z),
            top_half,
            table_yaw,
        ));
        let leg_half = Vector3::new(0.03, 0.03, (top_height - top_thickness) / 2.0);
        for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
            self.add(cuboid(
                on_table(
                    sx * (top_half.x - 0.07),
                    sy * (top_half.y - 0.07),
                    leg_half.z,
                ),
                leg_half,
                table_yaw,
            ));
        }
        let rng = &mut self.rng;
        let box_half = Vector3::new(0.16, 0.12, 0.1);
        let box_center = on_table(
            -0.25 + symmetric(rng, 0.05),
            0.1 + symmetric(rng, 0.05),
            top_height + box_half.z,
        );
        let box_yaw = table_yaw + symmetric(rng, 0.6);
        self.add(cuboid(box_center, box_half, box_yaw));
        let ball_radius = 0.11;
        let ball = Shape::Sphere {
            center: on_table(
                0.3 + symmetric(&mut self.rng, 0.05),
                -0.12,
                top_height + ball_radius,
            ),
            radius: ball_radius,
        };
        self.add(ball);
        let vase = Shape::Cylinder {
            base: on_table(0.05, -0.22 + symmetric(&mut self.rng, 0.04), top_height),
            radius: 0.06,
            height: 0.22,
        };
        self.add(vase);
    }

    /// Furniture along the walls, outside the agents' walking loop: a cabinet, a shelf, a bench,
    /// a big ball, a pillar, a bin and two stacked boxes. Returns the bench's position along its
    /// wall (a poster hangs above it).
    fn furniture_along_walls(&mut self) -> f64 {
        let cabinet_y = -0.2 + symmetric(&mut self.rng, 0.2);
        self.add(cuboid(
            Vector3::new(2.775, cabinet_y, 0.95),
            Vector3::new(0.225, 0.7, 0.95),
            0.0,
        ));
        let shelf_x = -0.6 + symmetric(&mut self.rng, 0.2);
        self.add(cuboid(
            Vector3::new(shelf_x, -2.3, 0.6),
            Vector3::new(0.8, 0.2, 0.6),
            0.0,
        ));
        let bench_y = 0.3 + symmetric(&mut self.rng, 0.2);
        self.add(cuboid(
            Vector3::new(-2.75, bench_y, 0.22),
            Vector3::new(0.25, 0.6, 0.22),
            0.0,
        ));
        let big_ball_radius = 0.4;
        let big_ball = Shape::Sphere {
            center: Vector3::new(
                2.35 + symmetric(&mut self.rng, 0.1),
                1.85 + symmetric(&mut self.rng, 0.1),
                big_ball_radius,
            ),
            radius: big_ball_radius,
        };
        self.add(big_ball);
        self.add(Shape::Cylinder {
            base: Vector3::new(-2.6, -2.1, 0.0),
            radius: 0.22,
            height: ROOM_MAX[2],
        });
        let bin = Shape::Cylinder {
            base: Vector3::new(
                -2.45 + symmetric(&mut self.rng, 0.08),
                1.95 + symmetric(&mut self.rng, 0.08),
                0.0,
            ),
            radius: 0.22,
            height: 0.65,
        };
        self.add(bin);
        let stack_x = 0.8 + symmetric(&mut self.rng, 0.2);
        let lower_half = Vector3::new(0.4, 0.25, 0.25);
        let lower_yaw = symmetric(&mut self.rng, 0.15);
        self.add(cuboid(
            Vector3::new(stack_x, 2.2, lower_half.z),
            lower_half,
            lower_yaw,
        ));
        let upper_half = Vector3::new(0.25, 0.2, 0.18);
        let upper_center = Vector3::new(
            stack_x + symmetric(&mut self.rng, 0.1),
            2.22,
            2.0 * lower_half.z + upper_half.z,
        );
        let upper_yaw = symmetric(&mut self.rng, 0.4);
        self.add(cuboid(upper_center, upper_half, upper_yaw));
        bench_y
    }

    /// Posters: thin boards on three walls, one above the bench.
    pub(super) fn posters(&mut self, bench_y: f64) {
        self.add(cuboid(
            Vector3::new(-2.99, bench_y, 1.5),
            Vector3::new(0.01, 0.5, 0.35),
            0.0,
        ));
        self.add(cuboid(
            Vector3::new(-0.8, 2.49, 1.55),
            Vector3::new(0.45, 0.01, 0.3),
            0.0,
        ));
        self.add(cuboid(
            Vector3::new(1.5, -2.49, 1.6),
            Vector3::new(0.4, 0.01, 0.5),
            0.0,
        ));
    }
}
