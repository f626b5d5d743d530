#!/usr/bin/env python3
"""Listens to what an agent publishes live over DDS (`[ros2] publish = true`), with Cyclone DDS
as rviz2 on a stock ROS 2 would: /tf, /tf_static, /<prefix>K/path and /<prefix>K/map. Ends after
--idle seconds without a message (once something came, and once --wait-for's topic was heard:
a consensus publishes its outputs only after its refinement, long after the agents' last tf) or
--timeout seconds in all, and prints
one JSON line: messages per topic, the last path's length and stamps, the last map's points and
fields, the child frames seen on /tf.

  python scripts/ros2/listen_outputs.py --agent 0 [--prefix agent] [--domain 0] [--idle 5] \
      [--map-topic /map] [--wait-for map]

Run it in the peers' environment: python="$(scripts/peers_venv.sh)".
"""

import argparse
import json
import sys
import time
from pathlib import Path as FilePath

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader, InvalidSample
from cyclonedds.topic import Topic
from cyclonedds.util import duration

sys.path.insert(0, str(FilePath(__file__).resolve().parent))
from ros2_idl import Path, PointCloud2, TFMessage  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agent", type=int, default=0)
    ap.add_argument("--prefix", default="agent")
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--map-topic", help="default /<prefix>K/map (the agent's); /map is the consensus's")
    ap.add_argument("--idle", type=float, default=5.0)
    ap.add_argument("--wait-for", choices=["tf", "tf_static", "path", "map"],
                    help="the idle end counts only once this topic was heard")
    ap.add_argument("--timeout", type=float, default=300.0)
    args = ap.parse_args()
    participant = DomainParticipant(args.domain)
    reliable = Qos(Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)), Policy.History.KeepLast(100))
    latched = Qos(Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)), Policy.History.KeepLast(1),
                  Policy.Durability.TransientLocal)
    latest = latched
    agent = f"/{args.prefix}{args.agent}"
    readers = {
        "tf": DataReader(participant, Topic(participant, "rt/tf", TFMessage), qos=reliable),
        "tf_static": DataReader(participant, Topic(participant, "rt/tf_static", TFMessage), qos=latched),
        "path": DataReader(participant, Topic(participant, f"rt{agent}/path", Path), qos=latest),
        "map": DataReader(participant, Topic(participant, "rt" + (args.map_topic or f"{agent}/map"), PointCloud2),
                          qos=latest),
    }
    seen = {name: 0 for name in readers}
    children = set()
    last_path = None
    last_map = None
    start = last = time.time()
    while time.time() - start < args.timeout:
        got = False
        for name, reader in readers.items():
            for sample in reader.take(N=100):
                if isinstance(sample, InvalidSample):
                    continue  # a writer left (an agent ended): no data
                got = True
                seen[name] += 1
                if name in ("tf", "tf_static"):
                    children.update(t.child_frame_id for t in sample.transforms)
                elif name == "path":
                    last_path = sample
                else:
                    last_map = sample
        now = time.time()
        if got:
            last = now
        elif sum(seen.values()) and (args.wait_for is None or seen[args.wait_for]) \
                and now - last > args.idle:
            break
        time.sleep(0.02)
    out = {"messages": seen, "tf_children": sorted(children)}
    if last_path is not None:
        stamps = [p.header.stamp.sec + p.header.stamp.nanosec * 1e-9 for p in last_path.poses]
        out["path"] = {"frame": last_path.header.frame_id, "poses": len(stamps),
                       "first_stamp": stamps[0] if stamps else None, "last_stamp": stamps[-1] if stamps else None}
    if last_map is not None:
        out["map"] = {"frame": last_map.header.frame_id, "points": last_map.width * last_map.height,
                      "fields": [f.name for f in last_map.fields], "bytes": len(last_map.data)}
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
