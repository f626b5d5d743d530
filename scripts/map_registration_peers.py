#!/usr/bin/env python3
"""The peers of `mac-ego3d bench map-registration --peers ...`: Open3D and splatreg register the
same pairs of maps as ours, side by side in one run.

The bench starts this driver once and talks to it over stdin/stdout, one JSON object per line:

    request: {"pair": "NAME", "source": "PATH.ply", "target": "PATH.ply",
              "splat_source": "PATH.ply", "splat_target": "PATH.ply", "methods": ["open3d", ...]}
    reply:   {"pair": "NAME", "results": {"open3d": RESULT, ...}}
    RESULT:  {"target_from_source": [16 numbers, row-major 4x4], "accepted": bool,
              "time_ms": float, "reason": str or null, "details": {...}}

Maps are 3DGS PLY files as the splats crate writes them (binary little-endian, 17 float properties:
x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3); the driver refuses anything else with the
file's name. `time_ms` is the registration's wall time alone (files are read before the clock
starts), on the threads the bench gave (OMP_NUM_THREADS for Open3D, torch.set_num_threads).

Methods, with fixed settings (docs/benchmarks.md quotes them with every figure):

* "open3d": Open3D's global registration as its documentation teaches it (the "Global
  registration" tutorial), on the maps' Gaussian means: voxel 5 cm; normals from neighbours within
  10 cm (at most 30); FPFH within 25 cm (at most 100); RANSAC over feature correspondences (mutual
  filter on), 3-point samples, edge-length checker 0.9, distance checker and inlier distance 7.5 cm,
  at most 4,000,000 iterations, confidence 0.999; then point-to-plane ICP at 2 cm on the maps
  downsampled at 2.5 cm. Open3D gives an answer for every pair; it counts as accepted when the ICP
  result's fitness over the smaller map (its points with a partner within 7.5 cm) is at least 0.1,
  the smallest overlap ours accepts without colour confirmation.
* "splatreg": splatreg.register(target, source, init=MODE, transform="se3") on the Gaussian maps
  "splat_source" and "splat_target" (means, log-scales, rotations, opacities, colours as written),
  MODE = --splatreg-init (default "robust", the mode splatreg's documentation recommends for
  metre-scale partial-overlap scans). The bench gives it the maps with one Gaussian per 5 cm cell:
  that registrar describes every Gaussian it gets (it takes its input as already decimated), and
  on the 2 cm maps the others get one pair took 137 s on two cores. Accepted unless splatreg flags
  the result itself: info["ambiguous"] true, info["success"] false, or info["confidence"] below
  0.5.

Run by hand: python scripts/map_registration_peers.py < requests.jsonl
"""

import argparse
import json
import math
import os
import struct
import sys
import time

PLY_PROPERTIES = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
]
SH_C0 = 0.28209479177387814

# Open3D's fixed settings (module documentation).
O3D_VOXEL_M = 0.05
O3D_NORMAL_RADIUS_M = 2 * O3D_VOXEL_M
O3D_NORMAL_MAX_NN = 30
O3D_FEATURE_RADIUS_M = 5 * O3D_VOXEL_M
O3D_FEATURE_MAX_NN = 100
O3D_DISTANCE_M = 1.5 * O3D_VOXEL_M
O3D_EDGE_LENGTH = 0.9
O3D_MAX_ITERATIONS = 4_000_000
O3D_CONFIDENCE = 0.999
O3D_ICP_VOXEL_M = 0.025
O3D_ICP_DISTANCE_M = 0.02
O3D_MIN_FITNESS = 0.1
SPLATREG_MIN_CONFIDENCE = 0.5


class MapError(Exception):
    pass


def read_gaussian_ply(path):
    """The rows of a 3DGS PLY of the splats crate as a list of 17-float tuples (standard library only)."""
    try:
        with open(path, "rb") as f:
            header = []
            while True:
                line = f.readline()
                if not line:
                    raise MapError(f"{path}: the PLY header has no end_header")
                text = line.decode("ascii", "replace").strip()
                header.append(text)
                if text == "end_header":
                    break
            data = f.read()
    except OSError as error:
        raise MapError(f"{path}: {error}") from error
    if not header or header[0] != "ply":
        raise MapError(f"{path}: not a PLY file")
    if "format binary_little_endian 1.0" not in header:
        raise MapError(f"{path}: only binary little-endian PLY is read")
    count = None
    properties = []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"] and len(parts) == 3:
            count = int(parts[2])
        elif parts[:1] == ["property"]:
            if len(parts) != 3 or parts[1] != "float":
                raise MapError(f"{path}: property line {line!r} is not a float property")
            properties.append(parts[2])
    if count is None:
        raise MapError(f"{path}: no vertex element")
    if properties != PLY_PROPERTIES:
        raise MapError(f"{path}: properties {properties} are not the splats crate's 3DGS layout")
    row = 4 * len(PLY_PROPERTIES)
    if len(data) < count * row:
        raise MapError(f"{path}: {count} vertices declared, the data holds {len(data) // row}")
    return list(struct.iter_unpack("<17f", data[: count * row]))


def as_arrays(rows):
    """Means, colours (RGB in [0, 1]), log-scales, quaternions (w first), opacity logits."""
    import numpy as np

    table = np.asarray(rows, dtype=np.float64).reshape(-1, len(PLY_PROPERTIES))
    colours = np.clip(0.5 + SH_C0 * table[:, 6:9], 0.0, 1.0)
    return {
        "means": table[:, 0:3],
        "colours": colours,
        "log_scales": table[:, 10:13],
        "quaternions": table[:, 13:17],
        "opacity_logits": table[:, 9],
    }


def open3d_register(source, target):
    import numpy as np
    import open3d as o3d

    def cloud(points):
        pc = o3d.geometry.PointCloud()
        pc.points = o3d.utility.Vector3dVector(points)
        return pc

    def features(pc):
        down = pc.voxel_down_sample(O3D_VOXEL_M)
        down.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=O3D_NORMAL_RADIUS_M, max_nn=O3D_NORMAL_MAX_NN)
        )
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            down,
            o3d.geometry.KDTreeSearchParamHybrid(radius=O3D_FEATURE_RADIUS_M, max_nn=O3D_FEATURE_MAX_NN),
        )
        return down, fpfh

    start = time.perf_counter()
    source_pc, target_pc = cloud(source["means"]), cloud(target["means"])
    (source_down, source_fpfh), (target_down, target_fpfh) = features(source_pc), features(target_pc)
    registration = o3d.pipelines.registration
    ransac = registration.registration_ransac_based_on_feature_matching(
        source_down,
        target_down,
        source_fpfh,
        target_fpfh,
        True,
        O3D_DISTANCE_M,
        registration.TransformationEstimationPointToPoint(False),
        3,
        [
            registration.CorrespondenceCheckerBasedOnEdgeLength(O3D_EDGE_LENGTH),
            registration.CorrespondenceCheckerBasedOnDistance(O3D_DISTANCE_M),
        ],
        registration.RANSACConvergenceCriteria(O3D_MAX_ITERATIONS, O3D_CONFIDENCE),
    )
    source_fine = source_pc.voxel_down_sample(O3D_ICP_VOXEL_M)
    target_fine = target_pc.voxel_down_sample(O3D_ICP_VOXEL_M)
    for pc in (source_fine, target_fine):
        pc.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=O3D_NORMAL_RADIUS_M, max_nn=O3D_NORMAL_MAX_NN)
        )
    icp = registration.registration_icp(
        source_fine,
        target_fine,
        O3D_ICP_DISTANCE_M,
        ransac.transformation,
        registration.TransformationEstimationPointToPlane(),
    )
    transform = np.asarray(icp.transformation)
    # Fitness over the smaller map: the source's share with a target partner, or the target's
    # with a source partner, whichever map is smaller.
    forward = registration.evaluate_registration(source_down, target_down, O3D_DISTANCE_M, transform)
    backward = registration.evaluate_registration(
        target_down, source_down, O3D_DISTANCE_M, np.linalg.inv(transform)
    )
    fitness = forward.fitness if len(source_down.points) <= len(target_down.points) else backward.fitness
    elapsed_ms = (time.perf_counter() - start) * 1e3
    accepted = fitness >= O3D_MIN_FITNESS
    return {
        "target_from_source": transform.reshape(-1).tolist(),
        "accepted": bool(accepted),
        "time_ms": elapsed_ms,
        "reason": None if accepted else f"fitness {fitness:.3f} below {O3D_MIN_FITNESS}",
        "details": {
            "ransac_fitness": ransac.fitness,
            "ransac_correspondences": len(ransac.correspondence_set),
            "icp_fitness": icp.fitness,
            "icp_rmse_m": icp.inlier_rmse,
            "fitness_of_smaller": fitness,
            "points": [len(source_down.points), len(target_down.points)],
        },
    }


def splatreg_register(source, target, init):
    import numpy as np
    import splatreg
    import torch

    def gaussians(m):
        f = lambda a: torch.as_tensor(a, dtype=torch.float32)
        return splatreg.Gaussians(
            means=f(m["means"]),
            quats=f(m["quaternions"]),
            scales=f(m["log_scales"]),
            opacities=f(m["opacity_logits"]),
            colors=f(m["colours"]),
            log_scales=True,
        )

    source_g, target_g = gaussians(source), gaussians(target)
    start = time.perf_counter()
    result = splatreg.register(target_g, source_g, init=init, transform="se3")
    elapsed_ms = (time.perf_counter() - start) * 1e3
    transform = result.T.detach().cpu().double().numpy()
    info = result.info
    reasons = []
    if info.get("ambiguous"):
        reasons.append("flagged ambiguous")
    if info.get("success") is False:
        reasons.append("no consensus")
    confidence = info.get("confidence")
    if confidence is not None and (not math.isfinite(confidence) or confidence < SPLATREG_MIN_CONFIDENCE):
        reasons.append(f"confidence {confidence:.3f} below {SPLATREG_MIN_CONFIDENCE}")
    if not np.all(np.isfinite(transform)):
        reasons.append("non-finite transform")
    details = {
        k: v
        for k, v in info.items()
        if isinstance(v, (bool, int, float, str)) and (not isinstance(v, float) or math.isfinite(v))
    }
    details["init"] = init
    return {
        "target_from_source": transform.reshape(-1).tolist(),
        "accepted": not reasons,
        "time_ms": elapsed_ms,
        "reason": "; ".join(reasons) or None,
        "details": details,
    }


def handle(request, args):
    def load(key):
        return as_arrays(read_gaussian_ply(request[key]))

    results = {}
    for method in request["methods"]:
        try:
            if method == "open3d":
                results[method] = open3d_register(load("source"), load("target"))
            elif method == "splatreg":
                results[method] = splatreg_register(
                    load("splat_source"), load("splat_target"), args.splatreg_init
                )
            else:
                results[method] = {"error": f"unknown method {method!r}"}
        except Exception as error:  # a peer's failure is reported for that pair, not fatal
            results[method] = {"error": f"{type(error).__name__}: {error}"}
    return {"pair": request["pair"], "results": results}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=0, help="threads per peer (0: leave as is)")
    parser.add_argument("--splatreg-init", default="robust", help="splatreg.register's init mode")
    args = parser.parse_args()
    # The replies own stdout: the libraries' own printing (Open3D's C++ warnings, e.g. "Too few
    # correspondences after mutual filter") goes to stderr instead, at the file-descriptor
    # level, so that no line of theirs is read as a reply.
    replies = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    if args.threads > 0:
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
        try:
            import torch

            torch.set_num_threads(args.threads)
        except ImportError:
            pass
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            reply = handle(json.loads(line), args)
        except (MapError, KeyError, ValueError) as error:
            reply = {"error": str(error)}
        replies.write(json.dumps(reply) + "\n")
        replies.flush()


if __name__ == "__main__":
    main()
