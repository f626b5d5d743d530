#!/usr/bin/env bash
# Map-quality levers, one at a time: a standalone agent at the paced mapping pace (the same map on
# any machine for a given seed, docs/method.md, One agent: Pace) on the same frames, once per
# lever, each run changing the configuration in one place from --config.
#
#   scripts/bench_map_levers.sh [--frames 0..300] [--rows baseline,half_resolution,...]
#       [--repeats 1] [--dataset DIR] [--config FILE] [--out DIR] [--json FILE] [--list]
#       [--bin-dir DIR]
#
# Rows (--list prints them with their overrides; default: every row but full_resolution, whose
# 640x480 iterations cost seconds each on a CPU device, and the budget_N curve):
#   baseline            --config as it is
#   budget_x2           twice the mapping iterations per keyframe: do iterations still limit?
#   budget_4, budget_8, budget_16, budget_32
#                       4 .. 32 iterations per keyframe instead of 100: quality against the
#                       iterations a slower mapper affords (the sensor pace gets what its
#                       machine's mapper does in the stream's duration; the curve says how fast
#                       a mapper must be to reach a quality in real time, docs/benchmarks.md)
#   half_resolution     keyframes optimised at 320x240 instead of 160x120
#   full_resolution     ... at 640x480
#   published_seed_scale  new Gaussians sized by the published depth rule, not the pixel footprint
#   all_tracking_seeds  tracking keyframes seed every point (the published rule), not only new ones
#   initial_opacity_0.5 new Gaussians start at opacity 0.5 instead of 0.1
#   footprint_1.0       new Gaussians' sigma 1 x the sample spacing instead of 2
#   depth_weight_0.5    depth term weight 0.5 instead of 2 (colour may pull geometry more)
#   keyframe_poses      the mapper refines keyframe poses photometrically with the map
#   seeds_and_resolution  all_tracking_seeds and half_resolution together
#   paced_best          seeds_and_resolution and keyframe_poses together
# --repeats N runs every row N times, interleaved (row 1, row 2, ..., row 1, ...). On one machine
# the runs of a row repeat bit for bit (the renderer sums gradients in a fixed order), so a
# spread means something else changed between runs (the driver, the build). The table then shows
# each row's median and its PSNR range.
# Each run's quality is what the agent itself reports (metrics.json): PSNR, SSIM, LPIPS and depth
# L1 of the real-time map on every 10th frame at full resolution against the dataset's images.
# Prints one table (row, overrides, PSNR, SSIM, LPIPS, depth L1, Gaussians, mapper iterations,
# wall time, ATE) and writes it as JSON to --json (default OUT/summary.json). Every run's outputs
# stay in --out (default: a new folder under $TMPDIR). Binaries: built first (release), or the
# mac-agent and mac-ego3d in --bin-dir as they are (test harnesses pass where cargo test put
# them). Dataset: $MAC_EGO3D_SHARED (default ../shared)/datasets/7scenes-redkitchen. Wall times
# depend on the machine and its load; the quality figures do not (paced).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/vulkan_env.sh

fail() { echo "[map-levers] $1" >&2; exit "${2:-1}"; }
usage() { sed -n '2,35p' "$0" | sed 's/^# \{0,1\}//'; }

# name|overrides (space-separated KEY=VALUE, as `mac-ego3d config --set`)
readonly ROWS='baseline|
budget_x2|mapping.iterations_per_keyframe=200
budget_4|mapping.iterations_per_keyframe=4
budget_8|mapping.iterations_per_keyframe=8
budget_16|mapping.iterations_per_keyframe=16
budget_32|mapping.iterations_per_keyframe=32
half_resolution|mapping.image_downscale=2
full_resolution|mapping.image_downscale=1
published_seed_scale|keyframes.seed_scale=published
all_tracking_seeds|keyframes.tracking_keyframe_seeds=all
initial_opacity_0.5|keyframes.initial_opacity=0.5
footprint_1.0|keyframes.footprint_sigma_per_spacing=1.0
depth_weight_0.5|mapping.weight_depth=0.5
keyframe_poses|mapping.refine_keyframe_poses=true
seeds_and_resolution|keyframes.tracking_keyframe_seeds=all mapping.image_downscale=2
paced_best|keyframes.tracking_keyframe_seeds=all mapping.image_downscale=2 mapping.refine_keyframe_poses=true'

shared="${MAC_EGO3D_SHARED:-../shared}"
frames=0..300
rows=""
repeats=1
dataset=""
config=configs/7scenes.toml
out=""
json=""
bin_dir=""
while [[ $# -gt 0 ]]; do
  case "$1" in
    --frames) frames="$2"; shift 2 ;;
    --rows) rows="$2"; shift 2 ;;
    --repeats) repeats="$2"; shift 2 ;;
    --dataset) dataset="$2"; shift 2 ;;
    --config) config="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --json) json="$2"; shift 2 ;;
    --bin-dir) bin_dir="$2"; shift 2 ;;
    --list) echo "$ROWS" | tr '|' '\t'; exit 0 ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; fail "unknown argument: $1" 2 ;;
  esac
done
dataset="${dataset:-$shared/datasets/7scenes-redkitchen}"
[[ -d "$dataset" ]] || fail "dataset folder not found: $dataset (set MAC_EGO3D_SHARED or --dataset)" 2
[[ -f "$config" ]] || fail "config not found: $config" 2
[[ "$repeats" =~ ^[1-9][0-9]*$ ]] || fail "--repeats takes a positive count, not '$repeats'" 2
if [[ -z "$rows" ]]; then
  rows="$(echo "$ROWS" | cut -d'|' -f1 | grep -vx full_resolution | grep -v '^budget_[0-9]' \
    | paste -sd, -)"
fi
out="${out:-$(mktemp -d "${TMPDIR:-/tmp}/map-levers.XXXXXX")}"
json="${json:-$out/summary.json}"
mkdir -p "$out"

overrides_of() {
  local line
  line="$(echo "$ROWS" | grep -m1 "^$1|")" || fail "unknown row: $1 (--list shows the rows)" 2
  echo "${line#*|}"
}
# Every row name is checked before the first run starts.
IFS=, read -r -a names <<<"$rows"
for name in "${names[@]}"; do overrides_of "$name" >/dev/null; done

if [[ -z "$bin_dir" ]]; then
  echo "[map-levers] building (scripts/build.sh: the tests' profile unless MAC_EGO3D_PROFILE says)" >&2
  bin_dir="$(bash scripts/build.sh)"
fi
for binary in mac-ego3d mac-agent; do
  [[ -x "$bin_dir/$binary" ]] || fail "$bin_dir/$binary is missing" 2
done
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"

for repeat in $(seq 1 "$repeats"); do
for name in "${names[@]}"; do
  run="$out/$name/$repeat"
  mkdir -p "$run"
  sets=()
  for pair in $(overrides_of "$name"); do sets+=(--set "$pair"); done
  "$bin_dir/mac-ego3d" config --config "$config" "${sets[@]}" --out "$run/config.toml"
  echo "[map-levers] $name: $(overrides_of "$name") -> $run" >&2
  "$bin_dir/mac-agent" --config "$run/config.toml" --dataset "$dataset" --frames "$frames" \
    --standalone --pace paced --out "$run" >"$run/agent.log" 2>&1 \
    || fail "$name: the agent failed (log: $run/agent.log)"
done
done

python3 - "$out" "$json" "$frames" "$repeats" "$ROWS" "${names[@]}" <<'EOF'
import json, statistics, sys
out, json_path, frames, repeats, table = sys.argv[1:6]
names = sys.argv[6:]
overrides = dict(line.split("|", 1) for line in table.splitlines())
keys = ["psnr", "ssim", "lpips", "depth_l1_cm", "gaussians", "mapping_iters", "keyframes", "wall_s", "ate_cm"]
rows = []
for name in names:
    runs = []
    for repeat in range(1, int(repeats) + 1):
        m = json.load(open(f"{out}/{name}/{repeat}/metrics.json"))
        m["ate_cm"] = 100.0 * m["ate_rmse_m"] if m.get("ate_rmse_m") is not None else None
        runs.append({k: m.get(k) for k in keys})
    median = {k: (statistics.median([r[k] for r in runs]) if all(r[k] is not None for r in runs) else None) for k in keys}
    psnrs = [r["psnr"] for r in runs]
    rows.append({"row": name, "overrides": overrides[name], **median,
                 "psnr_min": min(psnrs), "psnr_max": max(psnrs), "runs": runs})
fmt = lambda v, f: "-" if v is None else f.format(v)
print(f"map-quality levers, paced, frames {frames}, {repeats} run(s) per row (medians)")
print("| row | overrides | PSNR dB | PSNR range | SSIM | LPIPS | depth L1 cm | Gaussians | iterations | wall s | ATE cm |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for r in rows:
    print(f"| {r['row']} | {r['overrides'] or '-'} | {r['psnr']:.2f} | {r['psnr_min']:.2f}-{r['psnr_max']:.2f} | "
          f"{r['ssim']:.3f} | {fmt(r['lpips'], '{:.3f}')} | {fmt(r['depth_l1_cm'], '{:.2f}')} | "
          f"{r['gaussians']:.0f} | {r['mapping_iters']:.0f} | {r['wall_s']:.0f} | {fmt(r['ate_cm'], '{:.2f}')} |")
json.dump({"frames": frames, "pace": "paced", "repeats": int(repeats), "rows": rows}, open(json_path, "w"), indent=2)
print(f"JSON: {json_path}")
EOF
