#!/usr/bin/env python3
"""Publishes a dataset folder (TUM RGB-D or 7-Scenes layout) as a live ROS 2 camera over DDS, with
Eclipse Cyclone DDS (cyclonedds on PyPI: a DDS implementation independent of ours, and a ROS 2
RMW), the way realsense2_camera publishes with aligned depth: colour, depth and CameraInfo under a
namespace, on a DDS domain, with ROS 2's topic and type names (rt/..., sensor_msgs::msg::dds_::
Image_). No ROS installation is needed.

  python scripts/ros2/publish_dataset.py --dataset DIR --frames 0..300 --namespace /robot0 \
      [--domain 0] [--rate 30 | --sensor-pace] [--images raw|compressed] [--qos sensor|reliable] \
      [--stamps dataset|now] [--wait-subscribers 1] [--skip-depth-every N] [--duplicate-every N] \
      [--restart-after N] [--corrupt encoding|size|zero-stamp:EVERY] [--burst N]

Frames are read as scripts/ros2/dataset_to_bag.py reads them (the same association and stamps).
A TUM Kinect folder (freiburg1-3) also gets the depth's own CameraInfo, the Kinect's registration
pinhole, as the bag converter writes it.
--stamps now stamps each frame with the wall clock when it is sent (latency measurements);
dataset keeps the recording's stamps (the ground truth can be matched). Faults for tests:
--skip-depth-every N never sends every N-th depth image, --duplicate-every N sends every N-th
colour image twice, --restart-after N starts over from the first frame after N frames (a driver
restarted; stamps jump back), --corrupt spoils every EVERY-th frame as named, --burst N sends the
first N frames at 200 Hz. Prints one JSON line of what it sent at the end.

Raw images are serialised by cyclonedds in Python at about 30 ms per megabyte: use --rate 10 or
--images compressed for 30 Hz. Run it in the peers' environment: python="$(scripts/peers_venv.sh)".
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from cyclonedds.core import Qos, Policy
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from cyclonedds.util import duration

sys.path.insert(0, str(Path(__file__).resolve().parent))
import dataset_to_bag as folders  # noqa: E402  (its frame readers, shared)
from ros2_idl import CameraInfo, CompressedImage, Header, Image, Time  # noqa: E402


def header_at(stamp_s, frame_id=folders.OPTICAL_FRAME):
    ns = int(round(stamp_s * 1e9))
    return Header(stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True, type=Path)
    ap.add_argument("--frames", default="0..")
    ap.add_argument("--namespace", default="")
    ap.add_argument("--domain", type=int, default=0)
    pace = ap.add_mutually_exclusive_group()
    pace.add_argument("--rate", type=float, default=10.0, help="frames per second (default 10)")
    pace.add_argument("--sensor-pace", action="store_true", help="at the recording's own stamps")
    ap.add_argument("--images", choices=["raw", "compressed"], default="raw")
    ap.add_argument("--qos", choices=["sensor", "reliable"], default="sensor")
    ap.add_argument("--stamps", choices=["dataset", "now"], default="dataset")
    ap.add_argument("--wait-subscribers", type=int, default=1,
                    help="wait (up to 60 s) until this many subscribers matched the colour topic")
    ap.add_argument("--skip-depth-every", type=int, default=0)
    ap.add_argument("--duplicate-every", type=int, default=0)
    ap.add_argument("--restart-after", type=int, default=0)
    ap.add_argument("--corrupt", action="append", default=[], metavar="KIND:EVERY",
                    help="every EVERY-th frame bad: encoding (raw colour says yuv422), size (raw "
                         "colour's height one row more than its data), zero-stamp (both unstamped)")
    ap.add_argument("--burst", type=int, default=0, help="send the first N frames at 200 Hz")
    args = ap.parse_args()
    corrupt = {}
    for item in args.corrupt:
        kind, _, every = item.partition(":")
        if kind not in ("encoding", "size", "zero-stamp") or not every.isdigit() or int(every) < 1:
            sys.exit(f"--corrupt {item!r}: expected encoding:N, size:N or zero-stamp:N")
        corrupt[kind] = int(every)

    first, end = folders.parse_range(args.frames)
    folder = args.dataset
    tum = (folder / "rgb.txt").is_file()
    if tum:
        frames, _ = folders.tum_frames(folder, first, end)
        depth_units = 5000.0
        # A Kinect registers its depth into a pinhole of its own (not the colour lens): announced
        # on the depth's CameraInfo, as the bag converter writes it.
        depth_k = folders.ROS_DEFAULT_K if folders.freiburg_sensor(folder) else None
    else:
        frames, _ = folders.seven_scenes_frames(folder, first, end)
        depth_units = 1000.0
        depth_k = None
    if not frames:
        sys.exit(f"{folder}: no frames in {args.frames}")
    k_file = folder / "camera-intrinsics.txt"
    fx, fy, cx, cy = folders.read_k(k_file) if k_file.is_file() else (585.0, 585.0, 320.0, 240.0)
    distortion = list(folders.read_distortion(folder / "camera-distortion.txt"))

    ns = args.namespace.rstrip("/")
    compressed = args.images == "compressed"
    colour_name = ns + folders.COLOUR + ("/compressed" if compressed else "")
    depth_name = ns + folders.DEPTH + ("/compressedDepth" if compressed else "")
    info_name = ns + folders.COLOUR_INFO
    image_type = CompressedImage if compressed else Image
    if args.qos == "sensor":
        qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), Policy.Durability.Volatile)
    else:
        qos = Qos(Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)), Policy.History.KeepLast(5),
                  Policy.Durability.Volatile)
    participant = DomainParticipant(args.domain)

    def writer(name, kind):
        return DataWriter(participant, Topic(participant, "rt" + name, kind, qos=qos), qos=qos)

    colour_w = writer(colour_name, image_type)
    depth_w = writer(depth_name, image_type)
    info_w = writer(info_name, CameraInfo)
    depth_info_w = writer(ns + folders.DEPTH_INFO, CameraInfo) if depth_k else None

    deadline = time.time() + 60
    while colour_w.get_publication_matched_status().current_count < args.wait_subscribers:
        if time.time() > deadline:
            sys.exit(f"no subscriber matched {colour_name} within 60 s")
        time.sleep(0.05)
    # Discovery of the other two topics finishes about together; a moment more for it.
    time.sleep(0.5)

    sent = {"colour": 0, "depth": 0, "camera_info": 0, "duplicates": 0, "restarts": 0,
            "depth_skipped": 0, "frames": 0, "corrupted": {k: 0 for k in corrupt}, "topics": [colour_name, depth_name, info_name]}
    order = list(range(len(frames)))
    if args.restart_after:
        order = order[: args.restart_after] + order
    start = time.time()
    t0 = frames[0][0]
    for n, i in enumerate(order):
        stamp, colour_path, depth_path = frames[i]
        if args.restart_after and n == args.restart_after:
            sent["restarts"] += 1
            time.sleep(0.5)
            start = time.time()
        if n < args.burst:
            due = start + n / 200.0
        elif args.sensor_pace:
            due = start + (stamp - t0)
        else:
            due = start + (n if not args.restart_after or n < args.restart_after else n - args.restart_after) / args.rate
        time.sleep(max(0.0, due - time.time()))
        if args.stamps == "now":
            stamp = time.time()
        colour_bytes, rgb, raw_depth = folders.read_images(colour_path, depth_path, tum)
        height, width = rgb.shape[:2]
        info_w.write(CameraInfo(
            header=header_at(stamp), height=height, width=width, distortion_model="plumb_bob", d=distortion,
            k=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], r=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
            p=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]))
        sent["camera_info"] += 1
        if depth_info_w:
            dfx, dfy, dcx, dcy = depth_k
            depth_info_w.write(CameraInfo(
                header=header_at(stamp), height=height, width=width, distortion_model="plumb_bob",
                d=[0.0] * 5, k=[dfx, 0.0, dcx, 0.0, dfy, dcy, 0.0, 0.0, 1.0],
                r=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], p=[dfx, 0.0, dcx, 0.0, 0.0, dfy, dcy, 0.0, 0.0, 0.0, 1.0, 0.0]))
        if compressed:
            jpeg = folders.jpeg_bytes(colour_path, colour_bytes, rgb)
            colour_msg = CompressedImage(header=header_at(stamp), format="rgb8; jpeg compressed bgr8", data=jpeg)
            millimetres = np.round(raw_depth.astype(np.float64) * 1000.0 / depth_units).astype(np.uint16)
            depth_msg = CompressedImage(header=header_at(stamp), format="16UC1; compressedDepth png",
                                        data=bytes(12) + folders.png_bytes(millimetres))
        else:
            colour_msg = Image(header=header_at(stamp), height=height, width=width, encoding="rgb8",
                               is_bigendian=0, step=width * 3, data=rgb.tobytes())
            if tum:
                # TUM depth has 0.2 mm steps: metres as float (as TUM's own bags), not millimetres.
                metres = (raw_depth.astype(np.float64) / depth_units).astype("<f4")
                depth_msg = Image(header=header_at(stamp), height=height, width=width, encoding="32FC1",
                                  is_bigendian=0, step=width * 4, data=metres.tobytes())
            else:
                millimetres = raw_depth.astype("<u2")
                depth_msg = Image(header=header_at(stamp), height=height, width=width, encoding="16UC1",
                                  is_bigendian=0, step=width * 2, data=millimetres.tobytes())
        def bad(kind):
            every = corrupt.get(kind)
            hit = every is not None and n % every == every - 1
            if hit:
                sent["corrupted"][kind] += 1
            return hit

        if not compressed and bad("encoding"):
            colour_msg.encoding = "yuv422"
        if not compressed and bad("size"):
            colour_msg.height += 1
        if bad("zero-stamp"):
            colour_msg.header = header_at(0.0)
            depth_msg.header = header_at(0.0)
        colour_w.write(colour_msg)
        sent["colour"] += 1
        if args.duplicate_every and n % args.duplicate_every == args.duplicate_every - 1:
            colour_w.write(colour_msg)
            sent["duplicates"] += 1
        if args.skip_depth_every and n % args.skip_depth_every == args.skip_depth_every - 1:
            sent["depth_skipped"] += 1
        else:
            depth_w.write(depth_msg)
            sent["depth"] += 1
        sent["frames"] += 1
    # Best-effort samples still in flight when the participant goes are lost: let them land.
    time.sleep(1.0)
    sent["seconds"] = round(time.time() - start, 3)
    print(json.dumps(sent), flush=True)


if __name__ == "__main__":
    main()
