#!/usr/bin/env python3
"""The tracking peers of scripts/bench_vs_small_gicp.sh on exactly our tracker's input, and the
side-by-side table:

  small_gicp_odometry.py track --points DIR --voxel M --threads N --out TRAJ.tum > RUN.json
  small_gicp_odometry.py open3d --images DIR --out TRAJ.tum > RUN.json
  small_gicp_odometry.py report --runs DIR [--gt TUM] [--json FILE]

`track` needs numpy and small_gicp, `open3d` numpy and open3d (the peers' virtual environment,
scripts/peers_venv.sh); `report` and the helpers it uses need only the standard library, so the
repository's tests run them without either.

Open3D (`open3d`): its RGB-D odometry, frame to frame (each frame against the previous one, from
the identity), with the hybrid (photometric + geometric) Jacobian and its default options, on the
colour and depth images `mac-ego3d bench tracking --dump-images` wrote (undistorted where the
dataset is). A frame it reports unsuccessful keeps the previous pose and is flagged.

Failures (`report --gt`): a frame is a *real* failure when the step into it (from the trajectory's
previous frame) is wrong by more than 10 cm against the ground truth; it is *reported* when the
tracker flagged it (CONFIG-rN.flagged.txt: one timestamp per line; frames a tracker left out of
its trajectory are flagged too and cannot be scored).

Tracking (`track`), per frame, on exactly the points our tracker used (same depth frames, pixel
stride, truncation and intrinsics: they are our tracker's own back-projection):
  1. small_gicp.PointCloud, a KdTree and `--neighbours` nearest-neighbour covariances;
  2. G-ICP against a small_gicp.GaussianVoxelMap (VGICP: each voxel holds the Gaussian of the
     points inserted into it) from a constant-velocity guess (the previous pose advanced by the
     last frame-to-frame motion);
  3. the frame's points are inserted into the voxel map at the estimated pose (every frame, with
     the map's least-recently-used voxel removal: small_gicp's own incremental odometry).
The timed region is steps 1-3 (what `bench tracking` times for ours, except that ours also
back-projects the depth image, which favours small_gicp slightly); reading the points file and the
float32 -> float64 conversion small_gicp's API takes are outside it. The first frame only seeds the
map and is not timed, as in `bench tracking`.

The JSON printed by `track` uses `bench tracking --json`'s key names for the figures both have
(tracking_ms_median, tracking_ms_p90, points_ms_median, registration_ms_median,
map_update_ms_median), so `report` treats both trackers alike.
"""

import argparse
import glob
import json
import math
import os
import sys
import time

# The frames index `mac-ego3d bench tracking --dump-points` / `--dump-images` writes.
FRAMES_INDEX = "frames.tsv"
# A step wrong by more than this (metres) is a real tracking failure.
REAL_FAILURE_M = 0.10
# Configurations `report` compares ours against carry this prefix; ours is "ours".
SMALL_GICP_PREFIX = "small_gicp"
OURS = "ours"


def read_frames_index(points_dir):
    """(timestamp text, points file path) per frame, in tracking order."""
    path = os.path.join(points_dir, FRAMES_INDEX)
    frames = []
    with open(path, encoding="utf-8") as index:
        for number, line in enumerate(index, start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split("\t")
            if len(fields) != 2:
                raise ValueError(f"{path}:{number}: expected 'timestamp<TAB>file', got {line!r}")
            stamp, name = fields
            float(stamp)  # a malformed timestamp fails here, naming nothing worse than the line
            frames.append((stamp, os.path.join(points_dir, name)))
    if not frames:
        raise ValueError(f"{path}: no frames")
    return frames


def quantile(values, q):
    """Linear-interpolation quantile (numpy's default), q in [0, 1]; NaN for no values."""
    if not values:
        return math.nan
    ordered = sorted(values)
    position = q * (len(ordered) - 1)
    low = math.floor(position)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (position - low)


def median(values):
    return quantile(values, 0.5)


def tum_line(stamp, pose):
    """One TUM line (timestamp tx ty tz qx qy qz qw) of a 4x4 camera-to-world pose (nested lists)."""
    qx, qy, qz, qw = quaternion_from_rotation([row[:3] for row in pose[:3]])
    t = [pose[0][3], pose[1][3], pose[2][3]]
    return f"{stamp} {t[0]!r} {t[1]!r} {t[2]!r} {qx!r} {qy!r} {qz!r} {qw!r}"


def quaternion_from_rotation(r):
    """(x, y, z, w) of a 3x3 rotation matrix, w >= 0 (Shepperd's method: stable for any angle)."""
    trace = r[0][0] + r[1][1] + r[2][2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s, s / 4.0)
    elif r[0][0] > r[1][1] and r[0][0] > r[2][2]:
        s = 2.0 * math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2])
        q = (s / 4.0, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s, (r[2][1] - r[1][2]) / s)
    elif r[1][1] > r[2][2]:
        s = 2.0 * math.sqrt(1.0 + r[1][1] - r[0][0] - r[2][2])
        q = ((r[0][1] + r[1][0]) / s, s / 4.0, (r[1][2] + r[2][1]) / s, (r[0][2] - r[2][0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r[2][2] - r[0][0] - r[1][1])
        q = ((r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, s / 4.0, (r[1][0] - r[0][1]) / s)
    norm = math.sqrt(sum(c * c for c in q))
    sign = 1.0 if q[3] >= 0.0 else -1.0
    return tuple(sign * c / norm for c in q)


def track(args):
    import numpy as np
    import small_gicp

    frames = read_frames_index(args.points)
    world_from_camera = np.eye(4)
    velocity = np.eye(4)
    voxel_map = small_gicp.GaussianVoxelMap(args.voxel)
    poses, flagged = [], []
    times_ms, stage_ms, iterations = [], ([], [], []), []
    points = 0
    for stamp, path in frames:
        cloud_f32 = np.fromfile(path, dtype="<f4")
        if cloud_f32.size % 3:
            raise ValueError(f"{path}: {cloud_f32.size} floats, not x y z triples")
        xyz = cloud_f32.reshape(-1, 3).astype(np.float64)
        points += len(xyz)
        start = time.perf_counter()
        cloud = small_gicp.PointCloud(xyz)
        tree = small_gicp.KdTree(cloud, num_threads=args.threads)
        small_gicp.estimate_covariances(
            cloud, tree, num_neighbors=args.neighbours, num_threads=args.threads
        )
        covariances_done = time.perf_counter()
        if not poses:
            voxel_map.insert(cloud, world_from_camera)
            poses.append((stamp, world_from_camera.copy()))
            continue
        world_from_previous = world_from_camera
        result = small_gicp.align(
            voxel_map,
            cloud,
            init_T_target_source=world_from_previous @ velocity,
            max_correspondence_distance=args.max_correspondence,
            num_threads=args.threads,
            max_iterations=args.max_iterations,
            rotation_epsilon=args.rotation_epsilon,
            translation_epsilon=args.translation_epsilon,
        )
        registered = time.perf_counter()
        world_from_camera = np.array(result.T_target_source)
        velocity = np.linalg.inv(world_from_previous) @ world_from_camera
        voxel_map.insert(cloud, world_from_camera)
        end = time.perf_counter()
        if not result.converged:
            flagged.append(stamp)
        times_ms.append((end - start) * 1e3)
        stage_ms[0].append((covariances_done - start) * 1e3)
        stage_ms[1].append((registered - covariances_done) * 1e3)
        stage_ms[2].append((end - registered) * 1e3)
        iterations.append(result.iterations)
        poses.append((stamp, world_from_camera.copy()))
    write_tum(args.out, poses)
    write_flagged(args.out, flagged)
    report = {
        "failures_reported": len(flagged),
        "tracker": f"small_gicp {small_gicp_version()} GaussianVoxelMap (VGICP), frame-to-model",
        "voxel_m": args.voxel,
        "max_correspondence_m": args.max_correspondence,
        "covariance_neighbours": args.neighbours,
        "max_iterations": args.max_iterations,
        "rotation_epsilon_rad": args.rotation_epsilon,
        "translation_epsilon_m": args.translation_epsilon,
        "threads": args.threads,
        "frames": len(poses),
        "points_per_frame": points / len(poses),
        "tracking_ms_median": median(times_ms),
        "tracking_ms_p90": quantile(times_ms, 0.9),
        "tracking_ms_max": quantile(times_ms, 1.0),
        "points_ms_median": median(stage_ms[0]),
        "registration_ms_median": median(stage_ms[1]),
        "map_update_ms_median": median(stage_ms[2]),
        "iterations_median": median(iterations),
        "map_voxels": voxel_map.size(),
    }
    json.dump(report, sys.stdout, indent=2)
    print()


def read_images_index(images_dir):
    """(timestamp text, colour path, depth path) per frame, in tracking order, and the intrinsics."""
    path = os.path.join(images_dir, FRAMES_INDEX)
    frames = []
    with open(path, encoding="utf-8") as index:
        for number, line in enumerate(index, start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.split("\t")
            if len(fields) != 3:
                raise ValueError(f"{path}:{number}: expected 'timestamp<TAB>rgb<TAB>depth', got {line!r}")
            float(fields[0])
            frames.append((fields[0], os.path.join(images_dir, fields[1]), os.path.join(images_dir, fields[2])))
    if not frames:
        raise ValueError(f"{path}: no frames")
    with open(os.path.join(images_dir, "intrinsics.json"), encoding="utf-8") as f:
        intrinsics = json.load(f)
    return frames, intrinsics


def open3d_track(args):
    import numpy as np
    import open3d as o3d

    frames, k = read_images_index(args.images)
    camera = o3d.camera.PinholeCameraIntrinsic(
        k["width"], k["height"], k["fx"], k["fy"], k["cx"], k["cy"]
    )
    option = o3d.pipelines.odometry.OdometryOption()
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    world_from_camera = np.eye(4)
    previous = None
    poses, flagged, times_ms = [], [], []
    for stamp, rgb_path, depth_path in frames:
        colour = o3d.io.read_image(rgb_path)
        depth = o3d.io.read_image(depth_path)
        start = time.perf_counter()
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            colour, depth, depth_scale=1000.0, depth_trunc=args.truncation, convert_rgb_to_intensity=True
        )
        if previous is not None:
            success, previous_from_current, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
                rgbd, previous, camera, np.eye(4), jacobian, option
            )
            if success:
                world_from_camera = world_from_camera @ previous_from_current
            else:
                flagged.append(stamp)
            times_ms.append((time.perf_counter() - start) * 1e3)
        previous = rgbd
        poses.append((stamp, world_from_camera.copy()))
    write_tum(args.out, poses)
    write_flagged(args.out, flagged)
    report = {
        "tracker": f"Open3D {o3d.__version__} RGB-D odometry (hybrid term, frame to frame, default options)",
        "frames": len(poses),
        "tracking_ms_median": median(times_ms),
        "tracking_ms_p90": quantile(times_ms, 0.9),
        "tracking_ms_max": quantile(times_ms, 1.0),
        "failures_reported": len(flagged),
    }
    json.dump(report, sys.stdout, indent=2)
    print()


def write_tum(path, poses):
    with open(path, "w", encoding="utf-8") as out:
        out.write("# timestamp tx ty tz qx qy qz qw (camera-to-world)\n")
        for stamp, pose in poses:
            out.write(tum_line(stamp, pose.tolist()) + "\n")


def write_flagged(trajectory_path, stamps):
    """TRAJ.flagged.txt beside TRAJ.tum: the frames the tracker reported as failed."""
    with open(flagged_path(trajectory_path), "w", encoding="utf-8") as out:
        for stamp in stamps:
            out.write(f"{stamp}\n")


def flagged_path(trajectory_path):
    return trajectory_path[: -len(".tum")] + ".flagged.txt" if trajectory_path.endswith(".tum") else trajectory_path + ".flagged.txt"


def small_gicp_version():
    from importlib import metadata

    try:
        return metadata.version("small_gicp")
    except metadata.PackageNotFoundError:
        return "(version unknown)"


def read_tum(path):
    """[(timestamp, rotation rows, translation)] of a TUM file, in file order."""
    poses = []
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            values = [float(v) for v in line.split()]
            if len(values) != 8:
                raise ValueError(f"{path}:{number}: expected 8 numbers, got {len(values)}")
            t, tx, ty, tz, qx, qy, qz, qw = values
            poses.append((t, rotation_from_quaternion(qx, qy, qz, qw), [tx, ty, tz]))
    return poses


def rotation_from_quaternion(x, y, z, w):
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]


def step(a, b):
    """Translation of a^-1 b for poses (R, t): R_a^T (t_b - t_a), and R_a^T R_b."""
    (ra, ta), (rb, tb) = a, b
    d = [tb[i] - ta[i] for i in range(3)]
    translation = [sum(ra[k][i] * d[k] for k in range(3)) for i in range(3)]
    rotation = [[sum(ra[k][i] * rb[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
    return rotation, translation


def step_error_m(estimated, truth):
    """Translation of the step error (estimated step)^-1 (true step)."""
    (re, te), (_, tt) = estimated, truth
    d = [tt[i] - te[i] for i in range(3)]
    return math.sqrt(sum(sum(re[k][i] * d[k] for k in range(3)) ** 2 for i in range(3)))


def failures(trajectory_path, gt_path, flagged_stamps):
    """(real failures, real failures the tracker flagged) of a trajectory against ground truth."""
    truth = sorted((t, (r, x)) for t, r, x in read_tum(gt_path))
    truth_stamps = [t for t, _ in truth]

    def true_pose(t):
        import bisect

        i = bisect.bisect_left(truth_stamps, t)
        best = min(
            (j for j in (i - 1, i) if 0 <= j < len(truth)),
            key=lambda j: abs(truth_stamps[j] - t),
            default=None,
        )
        return truth[best][1] if best is not None and abs(truth_stamps[best] - t) <= 0.02 else None

    estimated = [(t, (r, x)) for t, r, x in read_tum(trajectory_path)]
    real = reported = 0
    for (t0, e0), (t1, e1) in zip(estimated, estimated[1:]):
        g0, g1 = true_pose(t0), true_pose(t1)
        if g0 is None or g1 is None:
            continue
        if step_error_m(step(e0, e1), step(g0, g1)) > REAL_FAILURE_M:
            real += 1
            reported += any(abs(t1 - f) < 1e-4 for f in flagged_stamps)
    return real, reported


def read_flagged(trajectory_path):
    try:
        with open(flagged_path(trajectory_path), encoding="utf-8") as f:
            return [float(line) for line in f if line.strip()]
    except FileNotFoundError:
        return []


def summarise(runs_dir, gt_path=None):
    """Per configuration: the medians over repeats of each run's figures.

    `runs_dir` holds CONFIG-rN.json (a run's `bench tracking --json` or `track` output) and
    CONFIG-rN.ate.json (`mac-ego3d eval ate --json` of that run's trajectory); with `gt_path`,
    CONFIG-rN.tum (the trajectory) and CONFIG-rN.flagged.txt (its flagged frames) are scored
    for real and reported failures.
    """
    by_config = {}
    for path in sorted(glob.glob(os.path.join(runs_dir, "*-r*.json"))):
        if path.endswith(".ate.json"):
            continue
        config, _, repeat = os.path.basename(path)[: -len(".json")].rpartition("-r")
        if not config or not repeat.isdigit():
            raise ValueError(f"{path}: expected a name CONFIG-rN.json")
        with open(path, encoding="utf-8") as f:
            run = json.load(f)
        ate_path = path[: -len(".json")] + ".ate.json"
        try:
            with open(ate_path, encoding="utf-8") as f:
                run["ate_rmse_m"] = json.load(f)["rmse"]
        except FileNotFoundError:
            raise ValueError(f"{ate_path}: missing (the ATE of {path})") from None
        trajectory = path[: -len(".json")] + ".tum"
        flagged = read_flagged(trajectory)
        run.setdefault("failures_reported", len(flagged))
        if gt_path:
            real, reported = failures(trajectory, gt_path, flagged)
            run["real_failures"], run["real_failures_unreported"] = real, real - reported
        by_config.setdefault(config, []).append(run)
    if OURS not in by_config:
        raise ValueError(f"{runs_dir}: no {OURS}-rN.json run")
    keys = [
        "tracking_ms_median",
        "tracking_ms_p90",
        "points_ms_median",
        "registration_ms_median",
        "map_update_ms_median",
        "iterations_median",
        "points_per_frame",
        "ate_rmse_m",
        "failures_reported",
        "real_failures",
        "real_failures_unreported",
    ]
    summary = {}
    for config, runs in by_config.items():
        row = {"repeats": len(runs), "frames": runs[0].get("frames")}
        for key in keys:
            values = [r[key] for r in runs if r.get(key) is not None]
            row[key] = median(values) if values else None
        row["tracking_ms_median_spread"] = [
            min(r["tracking_ms_median"] for r in runs),
            max(r["tracking_ms_median"] for r in runs),
        ]
        summary[config] = row
    ours = summary[OURS]
    for config, row in summary.items():
        if config != OURS and row["tracking_ms_median"]:
            row["ours_over_this_ms_median"] = ours["tracking_ms_median"] / row["tracking_ms_median"]
            row["ours_over_this_ms_p90"] = ours["tracking_ms_p90"] / row["tracking_ms_p90"]
    return summary


def table(summary):
    """The side-by-side table, ours first, as text."""
    header = (
        f"{'tracker':<24} {'runs':>4} {'ms med':>7} {'ms p90':>7} {'spread':>13} "
        f"{'ATE cm':>7} {'ours/this':>9} {'flagged':>7} {'real':>5} {'silent':>6}  "
        f"{'points/reg/map ms':>18}"
    )
    lines = [header]
    for config in [OURS] + sorted(c for c in summary if c != OURS):
        row = summary[config]
        low, high = row["tracking_ms_median_spread"]
        ratio = row.get("ours_over_this_ms_median")
        stages = "/".join(
            "-" if row[k] is None else f"{row[k]:.2f}"
            for k in ("points_ms_median", "registration_ms_median", "map_update_ms_median")
        )
        count = lambda key: "-" if row.get(key) is None else f"{row[key]:.0f}"
        lines.append(
            f"{config:<24} {row['repeats']:>4} {row['tracking_ms_median']:>7.2f} "
            f"{row['tracking_ms_p90']:>7.2f} {f'{low:.2f}-{high:.2f}':>13} "
            f"{row['ate_rmse_m'] * 100:>7.2f} {'' if ratio is None else f'{ratio:.2f}':>9} "
            f"{count('failures_reported'):>7} {count('real_failures'):>5} "
            f"{count('real_failures_unreported'):>6}  {stages:>18}"
        )
    return "\n".join(lines)


def peer_name(config):
    """A tracker's configuration as the figures table names it."""
    if config.startswith("small_gicp-voxel"):
        voxel_cm = float(config[len("small_gicp-voxel"):]) * 100
        return f"small_gicp ({voxel_cm:g} cm voxels)"
    return {"open3d": "Open3D RGB-D odometry"}.get(config, config)


def headline_figures(summary, label):
    """The run's figures for docs/figures (`mac-ego3d bench record-figures --from`): our ATE, and
    per peer its ATE and our time over its, medians over the repeats."""
    ours = summary[OURS]
    repeats = ours["repeats"]
    figures = [{"name": f"tracking ATE, {label} (median of {repeats})",
                "value": ours["ate_rmse_m"] * 100, "decimals": 2, "unit": "cm"}]
    for config, row in summary.items():
        if config == OURS:
            continue
        peer = peer_name(config)
        if row.get("ate_rmse_m") is not None:
            figures.append({"name": f"tracking ATE of {peer}, {label} (median of {row['repeats']})",
                            "value": row["ate_rmse_m"] * 100, "decimals": 2, "unit": "cm"})
        if row.get("ours_over_this_ms_median"):
            figures.append({"name": f"tracking time of ours / {peer}, {label} (medians of {repeats})",
                            "value": row["ours_over_this_ms_median"], "decimals": 2, "unit": ""})
    return figures


def report(args):
    summary = summarise(args.runs, args.gt)
    print(table(summary))
    if args.figures:
        with open(args.figures, "w", encoding="utf-8") as out:
            json.dump(headline_figures(summary, args.label), out, indent=2)
            out.write("\n")
    if args.json:
        document = {"context": json.loads(args.context) if args.context else {}, "trackers": summary}
        with open(args.json, "w", encoding="utf-8") as out:
            json.dump(document, out, indent=2)
            out.write("\n")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    t = commands.add_parser("track", help="small_gicp odometry over dumped points")
    t.add_argument("--points", required=True, help="folder written by bench tracking --dump-points")
    t.add_argument("--voxel", type=float, required=True, help="GaussianVoxelMap voxel size, m")
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--neighbours", type=int, default=10, help="k of the covariances (ours: 10)")
    t.add_argument(
        "--max-correspondence",
        type=float,
        default=1.0,
        help="small_gicp's max_correspondence_distance, m (its default)",
    )
    t.add_argument("--max-iterations", type=int, default=20, help="small_gicp's default")
    t.add_argument(
        "--rotation-epsilon",
        type=float,
        default=0.1 * math.pi / 180.0,
        help="convergence: rotation update, rad (small_gicp's default, 0.1 degrees)",
    )
    t.add_argument(
        "--translation-epsilon",
        type=float,
        default=1e-3,
        help="convergence: translation update, m (small_gicp's default)",
    )
    t.add_argument("--out", required=True, help="trajectory to write (TUM)")
    o = commands.add_parser("open3d", help="Open3D RGB-D odometry over dumped images")
    o.add_argument("--images", required=True, help="folder written by bench tracking --dump-images")
    o.add_argument("--truncation", type=float, default=10.0, help="depth truncation, m (ours: 10)")
    o.add_argument("--out", required=True, help="trajectory to write (TUM)")
    r = commands.add_parser("report", help="table and JSON of the runs in a folder")
    r.add_argument("--runs", required=True, help="folder of CONFIG-rN.json and CONFIG-rN.ate.json")
    r.add_argument("--json", help="write the summary here")
    r.add_argument("--gt", help="ground truth (TUM) to count real and reported failures against")
    r.add_argument("--context", help="JSON object stored as the summary's context")
    r.add_argument("--figures", help="write the headline figures here (bench record-figures' input)")
    r.add_argument("--label", default="", help="what the run is, in the figures' names")
    args = parser.parse_args(argv)
    try:
        {"track": track, "open3d": open3d_track, "report": report}[args.command](args)
    except (OSError, ValueError) as error:
        print(f"small_gicp_odometry.py: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
