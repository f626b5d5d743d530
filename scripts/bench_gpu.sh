#!/usr/bin/env bash
# The figures a GPU machine gives (docs/benchmarks.md): the splat kernels' speed and the
# redkitchen runs at full mapping resolution (640x480 keyframes, `mapping.image_downscale=1`).
#
#   scripts/bench_gpu.sh --bin-dir DIR [--dataset DIR] [--weights FILE] [--out DIR]
#       [--runs render,swarm_sensor,agent_sensor,swarm_paced] [--config FILE] [--end 1000]
#       [--gaussians 100000,1000000]
#
# Runs, each into OUT/NAME (default: all four, in this order):
#   render        `mac-ego3d bench render` at --gaussians (forward, backward, one
#                 optimisation iteration) -> OUT/render.json
#   swarm_sensor  the real-time 2-agent swarm (0..600 + 400..1000, the camera's own pace: an
#                 agent that falls behind drops frames and counts them)
#   agent_sensor  one real-time agent over 0..1000
# (--end N scales these ranges: 0..0.6N + 0.4N..N and 0..N, for a short check)
#   swarm_paced   the paced 2-agent swarm with every tracking-keyframe seed
# Each run is bounded by a timeout (RUN_TIMEOUT_S, default 300 s); a run that fails or times out
# is reported in the table and the others still run.
# Binaries: the mac-agent, mac-consensus and mac-ego3d in --bin-dir as they are (no build: the
# GPU machine may have no cargo). Dataset: --dataset, else $MAC_EGO3D_SHARED (default
# ../shared)/datasets/7scenes-redkitchen. --weights: the AlexNet file (place recognition, LPIPS).
# Prints one table and writes OUT/summary.json. The adapter each run used is in its log.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/vulkan_env.sh

fail() { echo "[bench-gpu] $1" >&2; exit "${2:-1}"; }
usage() { sed -n '2,25p' "$0" | sed 's/^# \{0,1\}//'; }

shared="${MAC_EGO3D_SHARED:-../shared}"
dataset=""
weights=""
out=""
bin_dir=""
runs=render,swarm_sensor,agent_sensor,swarm_paced
config=configs/7scenes.toml
end=1000
gaussians=100000,1000000
while [[ $# -gt 0 ]]; do
  case "$1" in
    --bin-dir) bin_dir="$2"; shift 2 ;;
    --dataset) dataset="$2"; shift 2 ;;
    --weights) weights="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --runs) runs="$2"; shift 2 ;;
    --config) config="$2"; shift 2 ;;
    --end) end="$2"; shift 2 ;;
    --gaussians) gaussians="$2"; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; fail "unknown argument: $1" 2 ;;
  esac
done
[[ -n "$bin_dir" ]] || fail "--bin-dir is required (the binaries to run)" 2
for binary in mac-agent mac-consensus mac-ego3d; do
  [[ -x "$bin_dir/$binary" ]] || fail "$bin_dir/$binary is missing" 2
done
dataset="${dataset:-$shared/datasets/7scenes-redkitchen}"
[[ -d "$dataset" ]] || fail "dataset folder not found: $dataset (set MAC_EGO3D_SHARED or --dataset)" 2
[[ -f "$config" ]] || fail "config not found: $config" 2
[[ "$end" =~ ^[1-9][0-9]*$ ]] || fail "--end takes a positive frame count, not '$end'" 2
weight_args=()
if [[ -n "$weights" ]]; then
  [[ -f "$weights" ]] || fail "--weights $weights: no such file" 2
  weight_args=(--descriptor-weights "$weights")
  export MAC_EGO3D_WEIGHTS="$weights"
fi
out="${out:-$(mktemp -d "${TMPDIR:-/tmp}/bench-gpu.XXXXXX")}"
mkdir -p "$out"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
timeout_s="${RUN_TIMEOUT_S:-300}"

IFS=, read -r -a names <<<"$runs"
for name in "${names[@]}"; do
  case "$name" in render | swarm_sensor | agent_sensor | swarm_paced) ;;
    *) fail "unknown run: $name (render, swarm_sensor, agent_sensor, swarm_paced)" 2 ;;
  esac
done

full_resolution=(--set mapping.image_downscale=1)
swarm_agents=(--agent "$dataset:0..$((end * 6 / 10))" --agent "$dataset:$((end * 4 / 10))..$end")
declare -A status=()
for name in "${names[@]}"; do
  echo "[bench-gpu] $name -> $out/$name" >&2
  mkdir -p "$out/$name"
  started=$(date +%s)
  rc=0
  case "$name" in
    render)
      timeout "$timeout_s" "$bin_dir/mac-ego3d" bench render --gaussians "$gaussians" --json \
        >"$out/render.json" 2>"$out/render/render.log" || rc=$? ;;
    swarm_sensor)
      timeout "$timeout_s" "$bin_dir/mac-ego3d" swarm --bin-dir "$bin_dir" --config "$config" \
        "${swarm_agents[@]}" "${full_resolution[@]}" "${weight_args[@]}" --out "$out/$name" \
        >"$out/$name/launch.log" 2>&1 || rc=$? ;;
    agent_sensor)
      { "$bin_dir/mac-ego3d" config --config "$config" "${full_resolution[@]}" --out "$out/$name/config.toml" &&
        timeout "$timeout_s" "$bin_dir/mac-agent" --config "$out/$name/config.toml" --dataset "$dataset" \
          --frames "0..$end" --standalone --pace sensor "${weight_args[@]}" --out "$out/$name"; } \
        >"$out/$name/agent.log" 2>&1 || rc=$? ;;
    swarm_paced)
      timeout "$timeout_s" "$bin_dir/mac-ego3d" swarm --bin-dir "$bin_dir" --config "$config" \
        "${swarm_agents[@]}" "${full_resolution[@]}" --set mapping.pace=paced \
        --set keyframes.tracking_keyframe_seeds=all "${weight_args[@]}" --out "$out/$name" \
        >"$out/$name/launch.log" 2>&1 || rc=$? ;;
  esac
  status[$name]="$rc $(($(date +%s) - started))"
  echo "[bench-gpu] $name: exit $rc after $(($(date +%s) - started)) s" >&2
done

status_args=()
for name in "${names[@]}"; do status_args+=("$name=${status[$name]}"); done
python3 - "$out" "${status_args[@]}" <<'EOF'
import json, os, sys
out = sys.argv[1]
rows = []
def load(path):
    try:
        return json.load(open(path))
    except (OSError, ValueError):
        return None
def fmt(value, spec):
    return format(value, spec) if isinstance(value, (int, float)) else "-"
for arg in sys.argv[2:]:
    name, state = arg.split("=", 1)
    rc, wall = (int(x) for x in state.split())
    row = {"run": name, "exit": rc, "wall_s": wall}
    if name == "render":
        row["bench_render"] = load(f"{out}/render.json")
    elif name.startswith("swarm"):
        m = load(f"{out}/{name}/metrics.json") or {}
        agents = [load(f"{out}/{name}/agent_{k}/metrics.json") or {} for k in range(2)]
        row.update({k: m.get(k) for k in ("psnr", "ssim", "lpips", "depth_l1_cm", "ate_joint_rmse_m")})
        row["frames_dropped"] = [a.get("frames_dropped") for a in agents]
        row["mapping_iters"] = [a.get("mapping_iters") for a in agents]
        row["agent_psnr"] = [a.get("psnr") for a in agents]
    else:
        m = load(f"{out}/{name}/metrics.json") or {}
        row.update({k: m.get(k) for k in ("psnr", "ssim", "lpips", "depth_l1_cm", "frames_dropped", "mapping_iters")})
        row["ate_joint_rmse_m"] = m.get("ate_rmse_m")
    rows.append(row)
json.dump(rows, open(f"{out}/summary.json", "w"), indent=2)
print(f"{'run':<14}{'exit':>5}{'wall s':>8}{'PSNR':>8}{'SSIM':>7}{'LPIPS':>7}{'ATE cm':>8}  dropped / mapper iterations")
for r in rows:
    if r["run"] == "render":
        print(f"{'render':<14}{r['exit']:>5}{r['wall_s']:>8}  (OUT/render.json)")
        continue
    ate = r.get("ate_joint_rmse_m")
    print(f"{r['run']:<14}{r['exit']:>5}{r['wall_s']:>8}{fmt(r.get('psnr'), '.2f'):>8}{fmt(r.get('ssim'), '.3f'):>7}"
          f"{fmt(r.get('lpips'), '.3f'):>7}{fmt(ate * 100 if ate is not None else None, '.2f'):>8}  "
          f"{r.get('frames_dropped')} / {r.get('mapping_iters')}")
EOF
echo "[bench-gpu] outputs in $out (summary.json)" >&2
