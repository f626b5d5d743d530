#!/usr/bin/env python3
"""Writes a dataset folder (TUM RGB-D or 7-Scenes layout) as a rosbag2 bag, with the `rosbags`
package (an implementation independent of ours), the way a ROS 2 camera driver would record it:
the realsense2_camera topic names with aligned depth, a CameraInfo per frame, and the ground truth
on /gt_pose (geometry_msgs/PoseStamped, frame "world") and on /tf (world -> gt_camera).

  python scripts/ros2/dataset_to_bag.py --dataset DIR --frames 0..200 --out BAG \
      --storage mcap|sqlite3 --images raw|compressed

raw: colour rgb8, depth 16UC1 millimetres (7-Scenes) or 32FC1 metres (TUM, whose depth PNGs have
0.2 mm steps; TUM's own bags carry 32FC1). compressed: colour as JPEG (a dataset's own JPEG bytes
unchanged; PNG colour encoded at quality 95) on <colour>/compressed, depth as compressed_depth_image_
transport's 16UC1 PNG in millimetres on <depth>/compressedDepth.

Frames are what mac-ego3d's folder reader yields: TUM colour images with the depth image nearest in
stamp within 20 ms (rows of that association, numbered from 0); 7-Scenes frames by number. 7-Scenes
has no clock: its frame N is stamped 1.7e9 s + N / 30 (a ROS stamp of zero means "no stamp").
A TUM recording from a Freiburg sensor has depth registered to the Kinect's factory pinhole, not to
the calibrated colour lens: its depth topic gets a CameraInfo of its own with that pinhole.

For tests of damaged bags: --corrupt wrong-type:N writes a PoseStamped in place of the N-th colour
image (the topic's type stays Image), --corrupt encoding:N gives the N-th raw colour image the
encoding "yuv422", --no-camera-info leaves the CameraInfo topics out.

Run it in the peers' environment: python="$(scripts/peers_venv.sh)".
"""

import argparse
import io
import math
import re
import sys
from pathlib import Path

import numpy as np
from PIL import Image as PILImage
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
T = TYPESTORE.types
COLOUR = "/camera/camera/color/image_raw"
DEPTH = "/camera/camera/aligned_depth_to_color/image_raw"
COLOUR_INFO = "/camera/camera/color/camera_info"
DEPTH_INFO = "/camera/camera/aligned_depth_to_color/camera_info"
OPTICAL_FRAME = "camera_color_optical_frame"
SEVEN_SCENES_EPOCH_S = 1.7e9
ASSOCIATION_S = 0.02
ROS_DEFAULT_K = (525.0, 525.0, 319.5, 239.5)


def parse_range(text):
    match = re.fullmatch(r"(\d*)\.\.(\d*)", text)
    if not match:
        sys.exit(f"--frames {text!r}: expected FIRST..END")
    return int(match.group(1) or 0), (int(match.group(2)) if match.group(2) else None)


def read_k(path):
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    k = np.array(rows, dtype=float)
    return k[0, 0], k[1, 1], k[0, 2], k[1, 2]


def read_distortion(path):
    if not path.is_file():
        return [0.0] * 5
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            return [float(v) for v in line.split()]
    return [0.0] * 5


def nearest(stamps, t):
    i = int(np.searchsorted(stamps, t))
    best = None
    for j in (i - 1, i):
        if 0 <= j < len(stamps) and (best is None or abs(stamps[j] - t) < abs(stamps[best] - t)):
            best = j
    return best if best is not None and abs(stamps[best] - t) <= ASSOCIATION_S else None


def read_list(path):
    out = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            stamp, name = line.split()
            out.append((float(stamp), path.parent / name))
    out.sort(key=lambda e: e[0])
    return out


def freiburg_sensor(folder):
    def find(text):
        text = text.lower()
        for n in (1, 2, 3):
            if f"freiburg{n}" in text or f"fr{n}" in re.split(r"[^a-z0-9]", text):
                return n
        return None

    found = find(folder.resolve().name)
    if found is None:
        comments = " ".join(l for l in (folder / "depth.txt").read_text().splitlines() if l.startswith("#"))
        found = find(comments)
    return found


def quaternion_of(r):
    """Unit quaternion (x, y, z, w) of a rotation matrix."""
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = math.sqrt(trace + 1.0) * 2
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax([r[0, 0], r[1, 1], r[2, 2]]))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return tuple(q)


def tum_frames(folder, first, end):
    rgb = read_list(folder / "rgb.txt")
    depth = read_list(folder / "depth.txt")
    depth_stamps = np.array([d[0] for d in depth])
    frames = []
    for stamp, rgb_path in rgb:
        d = nearest(depth_stamps, stamp)
        if d is not None:
            frames.append((stamp, rgb_path, depth[d][1]))
    frames = frames[first:end]
    gt = []
    gt_path = folder / "groundtruth.txt"
    if gt_path.is_file():
        lo, hi = frames[0][0] - 0.1, frames[-1][0] + 0.1
        for line in gt_path.read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                v = [float(x) for x in line.split()]
                if lo <= v[0] <= hi:
                    gt.append((v[0], (v[1], v[2], v[3]), (v[4], v[5], v[6], v[7])))
    return frames, gt


def seven_scenes_frames(folder, first, end):
    numbers = sorted(
        int(m.group(1))
        for p in folder.iterdir()
        if (m := re.fullmatch(r"frame-(\d+)\.color\.(png|jpg)", p.name))
    )
    frames, gt = [], []
    for n in numbers:
        if n < first or (end is not None and n >= end):
            continue
        colour = next(folder / f"frame-{n:06d}.color.{e}" for e in ("png", "jpg") if (folder / f"frame-{n:06d}.color.{e}").is_file())
        stamp = SEVEN_SCENES_EPOCH_S + n / 30.0
        frames.append((stamp, colour, folder / f"frame-{n:06d}.depth.png"))
        pose = np.loadtxt(folder / f"frame-{n:06d}.pose.txt")
        gt.append((stamp, tuple(pose[:3, 3]), quaternion_of(pose[:3, :3])))
    return frames, gt


def stamp_of(t):
    ns = int(round(t * 1e9))
    return T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), ns


def header(t, frame=OPTICAL_FRAME):
    stamp, _ = stamp_of(t)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def camera_info(t, k, d, width, height):
    fx, fy, cx, cy = k
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(t), height=height, width=width, distortion_model="plumb_bob",
        d=np.array(d, dtype=np.float64),
        k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
        r=np.array([1, 0, 0, 0, 1, 0, 0, 0, 1], dtype=np.float64),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64),
        binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def read_images(colour_path, depth_path, tum):
    """(the colour file's bytes, its RGB pixels, the raw 16-bit depth with 7-Scenes' 65535
    "invalid" made 0)."""
    colour_bytes = colour_path.read_bytes()
    rgb = np.array(PILImage.open(io.BytesIO(colour_bytes)).convert("RGB"))
    raw_depth = np.array(PILImage.open(depth_path), dtype=np.uint16)
    if not tum:
        raw_depth[raw_depth == 65535] = 0
    return colour_bytes, rgb, raw_depth


def jpeg_bytes(colour_path, colour_bytes, rgb):
    """The colour image as JPEG: a dataset's own JPEG bytes unchanged, PNG colour at quality 95."""
    if colour_path.suffix == ".jpg":
        return colour_bytes
    out = io.BytesIO()
    PILImage.fromarray(rgb).save(out, format="JPEG", quality=95)
    return out.getvalue()


def png_bytes(array):
    out = io.BytesIO()
    PILImage.fromarray(array).save(out, format="PNG")
    return out.getvalue()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True, type=Path)
    ap.add_argument("--frames", default="0..")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap")
    ap.add_argument("--images", choices=["raw", "compressed"], default="raw")
    ap.add_argument("--no-ground-truth", action="store_true")
    ap.add_argument("--no-camera-info", action="store_true")
    ap.add_argument("--corrupt", action="append", default=[], metavar="KIND:N",
                    help="wrong-type:N or encoding:N (the N-th colour message)")
    args = ap.parse_args()
    corrupt = {}
    for item in args.corrupt:
        kind, _, index = item.partition(":")
        if kind not in ("wrong-type", "encoding") or not index.isdigit():
            sys.exit(f"--corrupt {item!r}: expected wrong-type:N or encoding:N")
        corrupt[int(index)] = kind
    first, end = parse_range(args.frames)
    folder = args.dataset
    tum = (folder / "rgb.txt").is_file()
    if tum:
        frames, gt = tum_frames(folder, first, end)
        depth_units = 5000.0
        sensor = freiburg_sensor(folder)
        depth_k = ROS_DEFAULT_K if sensor else None
    else:
        frames, gt = seven_scenes_frames(folder, first, end)
        depth_units = 1000.0
        depth_k = None
    if not frames:
        sys.exit(f"{folder}: no frames in {args.frames}")
    k_file = folder / "camera-intrinsics.txt"
    k = read_k(k_file) if k_file.is_file() else (585.0, 585.0, 320.0, 240.0)
    distortion = read_distortion(folder / "camera-distortion.txt")
    storage = StoragePlugin.MCAP if args.storage == "mcap" else StoragePlugin.SQLITE3
    compressed = args.images == "compressed"
    with Writer(args.out, version=8, storage_plugin=storage) as writer:
        def connection(topic, msgtype):
            return writer.add_connection(topic, msgtype, typestore=TYPESTORE)

        if compressed:
            colour_c = connection(COLOUR + "/compressed", "sensor_msgs/msg/CompressedImage")
            depth_c = connection(DEPTH + "/compressedDepth", "sensor_msgs/msg/CompressedImage")
        else:
            colour_c = connection(COLOUR, "sensor_msgs/msg/Image")
            depth_c = connection(DEPTH, "sensor_msgs/msg/Image")
        info_c = None if args.no_camera_info else connection(COLOUR_INFO, "sensor_msgs/msg/CameraInfo")
        depth_info_c = connection(DEPTH_INFO, "sensor_msgs/msg/CameraInfo") if depth_k and info_c else None
        if gt and not args.no_ground_truth:
            gt_c = connection("/gt_pose", "geometry_msgs/msg/PoseStamped")
            tf_c = connection("/tf", "tf2_msgs/msg/TFMessage")
            for t, (x, y, z), (qx, qy, qz, qw) in gt:
                _, ns = stamp_of(t)
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                )
                stamped = T["geometry_msgs/msg/PoseStamped"](header=header(t, "world"), pose=pose)
                writer.write(gt_c, ns, TYPESTORE.serialize_cdr(stamped, "geometry_msgs/msg/PoseStamped"))
                transform = T["geometry_msgs/msg/TransformStamped"](
                    header=header(t, "world"), child_frame_id="gt_camera",
                    transform=T["geometry_msgs/msg/Transform"](
                        translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                        rotation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                    ),
                )
                tf = T["tf2_msgs/msg/TFMessage"](transforms=[transform])
                writer.write(tf_c, ns, TYPESTORE.serialize_cdr(tf, "tf2_msgs/msg/TFMessage"))
        for number, (t, colour_path, depth_path) in enumerate(frames):
            _, ns = stamp_of(t)
            colour_bytes, rgb, raw_depth = read_images(colour_path, depth_path, tum)
            height, width = rgb.shape[:2]
            if info_c:
                info = camera_info(t, k, distortion, width, height)
                writer.write(info_c, ns, TYPESTORE.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            if depth_info_c:
                depth_info = camera_info(t, depth_k, [0.0] * 5, width, height)
                writer.write(depth_info_c, ns, TYPESTORE.serialize_cdr(depth_info, "sensor_msgs/msg/CameraInfo"))
            if compressed:
                jpeg = jpeg_bytes(colour_path, colour_bytes, rgb)
                colour_msg = T["sensor_msgs/msg/CompressedImage"](
                    header=header(t), format="rgb8; jpeg compressed bgr8", data=np.frombuffer(jpeg, dtype=np.uint8))
                millimetres = np.round(raw_depth.astype(np.float64) * 1000.0 / depth_units).astype(np.uint16)
                config_header = np.zeros(12, dtype=np.uint8)
                depth_msg = T["sensor_msgs/msg/CompressedImage"](
                    header=header(t), format="16UC1; compressedDepth png",
                    data=np.concatenate([config_header, np.frombuffer(png_bytes(millimetres), dtype=np.uint8)]))
                msgtype = "sensor_msgs/msg/CompressedImage"
            else:
                colour_msg = T["sensor_msgs/msg/Image"](
                    header=header(t), height=height, width=width, encoding="rgb8", is_bigendian=0,
                    step=width * 3, data=rgb.reshape(-1))
                if tum:
                    metres = (raw_depth.astype(np.float64) / depth_units).astype(np.float32)
                    depth_msg = T["sensor_msgs/msg/Image"](
                        header=header(t), height=height, width=width, encoding="32FC1", is_bigendian=0,
                        step=width * 4, data=metres.view(np.uint8).reshape(-1))
                else:
                    depth_msg = T["sensor_msgs/msg/Image"](
                        header=header(t), height=height, width=width, encoding="16UC1", is_bigendian=0,
                        step=width * 2, data=raw_depth.astype("<u2").view(np.uint8).reshape(-1))
                msgtype = "sensor_msgs/msg/Image"
            if corrupt.get(number) == "encoding" and not compressed:
                colour_msg.encoding = "yuv422"
            if corrupt.get(number) == "wrong-type":
                pose = T["geometry_msgs/msg/PoseStamped"](header=header(t), pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
                writer.write(colour_c, ns, TYPESTORE.serialize_cdr(pose, "geometry_msgs/msg/PoseStamped"))
            else:
                writer.write(colour_c, ns, TYPESTORE.serialize_cdr(colour_msg, msgtype))
            writer.write(depth_c, ns, TYPESTORE.serialize_cdr(depth_msg, msgtype))
            if number % 100 == 0:
                print(f"[dataset_to_bag] frame {number}/{len(frames)}", file=sys.stderr)
    print(f"[dataset_to_bag] {args.out}: {len(frames)} frames, {len(gt)} ground-truth poses", file=sys.stderr)


if __name__ == "__main__":
    main()
