#!/usr/bin/env bash
# Tracking speed and accuracy side by side: ours (`mac-ego3d bench tracking`), small_gicp's
# frame-to-model odometry and Open3D's RGB-D odometry (scripts/small_gicp_odometry.py), on the
# same input, in one run. --frames takes a stride (0..1000:10) for fast-motion runs.
#
#   scripts/bench_vs_small_gicp.sh [--frames 0..300[:STEP]] [--threads 2] [--voxels 0.05,0.02]
#       [--repeats 5] [--omp-wait-policy passive] [--no-open3d] [--dataset DIR] [--gt TUM]
#       [--config FILE] [--out DIR] [--json FILE] [--bin MAC_EGO3D]
#       [--figures FILE --figures-section HEADING [--figures-label TEXT] [--machine TEXT]]
#
# Same input: a first, untimed run of ours writes every frame's points as our tracker
# back-projected them (`bench tracking --dump-points`: same depth frames, pixel stride, truncation
# and intrinsics, from --config, default configs/7scenes.toml) and small_gicp tracks those, and
# its images (`--dump-images`: undistorted where the dataset is), which Open3D tracks. Same
# threads: RAYON_NUM_THREADS and OMP_NUM_THREADS = --threads, and small_gicp's num_threads too.
# small_gicp's OpenMP threads wait passively by default (--omp-wait-policy, OMP_WAIT_POLICY), as
# rayon's idle workers sleep: on a machine shared with other work, spinning OpenMP threads wait
# for a descheduled peer and small_gicp measures far slower than it is (docs/benchmarks.md).
# Then --repeats rounds, each running ours and small_gicp at every --voxels size (its
# GaussianVoxelMap voxel, m) back to back, so load changes spread over all of them. Both
# trajectories are scored by the same code, `mac-ego3d eval ate` against --gt (default:
# DIR/groundtruth_tum.txt of the dataset).
# Prints one table (per tracker: medians over the repeats of ms/frame median and p90, ATE RMSE,
# ours / peer ms ratio, frames the tracker flagged as failed, real failures (steps wrong by more
# than 10 cm against --gt) and those of them it did not flag, stage medians) and writes it as JSON
# to --json (default
# OUT/summary.json). Every run's files stay in --out (default: a new folder under $TMPDIR).
# --figures writes the headline figures (our ATE; each peer's ATE and our time over its) into a
# docs/figures file through `mac-ego3d bench record-figures`, as the bench commands' --figures
# do (--figures-label: what the run is, default the dataset's folder name and frames).
#
# small_gicp and numpy come from the peers' virtual environment (scripts/peers_venv.sh: pinned,
# hash-checked PyPI wheels, outside the repository). Without PyPI the script says so and exits 3.
# Dataset: $MAC_EGO3D_SHARED (default ../shared). --bin names a built mac-ego3d to time (default:
# scripts/build.sh's build).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/vulkan_env.sh
repo="$(pwd)"

fail() { echo "[vs-small_gicp] $1" >&2; exit "${2:-1}"; }
usage() { sed -n '2,35p' "$0" | sed 's/^# \{0,1\}//'; }

shared="${MAC_EGO3D_SHARED:-../shared}"
frames=0..300
threads=2
voxels=0.05,0.02
repeats=5
omp_wait_policy=passive
open3d=1
dataset="$shared/datasets/7scenes-redkitchen"
gt=""
config=configs/7scenes.toml
out=""
json=""
bin=""
source scripts/figure_options.sh
take_figure_options "$@" || exit 2
set -- "${figure_rest[@]}"
command_line="scripts/bench_vs_small_gicp.sh $*"
while (($#)); do
  case "$1" in
    --frames) frames="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --voxels) voxels="$2"; shift 2 ;;
    --repeats) repeats="$2"; shift 2 ;;
    --omp-wait-policy) omp_wait_policy="$2"; shift 2 ;;
    --no-open3d) open3d=0; shift ;;
    --dataset) dataset="$2"; shift 2 ;;
    --gt) gt="$2"; shift 2 ;;
    --config) config="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --json) json="$2"; shift 2 ;;
    --bin) bin="$2"; shift 2 ;;
    -h | --help) usage; exit 0 ;;
    *) usage >&2; fail "unknown argument: $1" 2 ;;
  esac
done
[[ "$threads" =~ ^[1-9][0-9]*$ ]] || fail "--threads $threads: not a positive integer" 2
[[ "$repeats" =~ ^[1-9][0-9]*$ ]] || fail "--repeats $repeats: not a positive integer" 2
[[ "$omp_wait_policy" == active || "$omp_wait_policy" == passive ]] ||
  fail "--omp-wait-policy $omp_wait_policy: expected active or passive" 2
IFS=',' read -ra voxel_list <<<"$voxels"
for v in "${voxel_list[@]}"; do
  [[ "$v" =~ ^[0-9]*\.?[0-9]+$ ]] || fail "--voxels: $v is not a size in metres" 2
done
[[ -d "$dataset" ]] || fail "--dataset $dataset: no such folder (set MAC_EGO3D_SHARED to the folder that holds datasets/)" 2
if [[ -z "$gt" ]]; then
  gt="$dataset/groundtruth_tum.txt"
  [[ -f "$gt" ]] || gt="$dataset/groundtruth.txt"
fi
[[ -f "$gt" ]] || fail "--gt $gt: no such file (the ground truth both trajectories are scored against)" 2
[[ -f "$config" ]] || fail "--config $config: no such file" 2
command -v python3 >/dev/null 2>&1 || fail "python3 is required (with venv and pip) but is not on PATH"
[[ -n "$out" ]] || out="$(mktemp -d "${TMPDIR:-/tmp}/bench_vs_small_gicp.XXXXXX")"
mkdir -p "$out/runs"
out="$(cd "$out" && pwd)"
json="${json:-$out/summary.json}"

# --- small_gicp from the peers' virtual environment, outside the repository ---------------------
python="$(scripts/peers_venv.sh)" || exit $?

# --- our binary ------------------------------------------------------------------------------
if [[ -z "$bin" ]]; then
  echo "[vs-small_gicp] building (scripts/build.sh: the tests' profile unless MAC_EGO3D_PROFILE says)" >&2
  bin="$(bash scripts/build.sh)/mac-ego3d"
fi
[[ -x "$bin" ]] || fail "--bin $bin: not an executable" 2

export RAYON_NUM_THREADS="$threads" OMP_NUM_THREADS="$threads" OMP_WAIT_POLICY="$omp_wait_policy"
load_before="$(cut -d' ' -f1-3 /proc/loadavg 2>/dev/null || echo unknown)"
echo "[vs-small_gicp] $dataset frames $frames, $threads threads, $repeats repeats; load $load_before; files in $out" >&2

# Untimed: our points for small_gicp (the file writes would disturb the timings).
"$bin" bench tracking --dataset "$dataset" --frames "$frames" --config "$config" \
  --dump-points "$out/points" --dump-images "$out/images" --json >"$out/dump-run.json"

ate() { "$bin" eval ate --gt "$gt" --est "$1" --json >"${1%.tum}.ate.json"; }
for ((r = 1; r <= repeats; r++)); do
  echo "[vs-small_gicp] round $r/$repeats" >&2
  run="$out/runs/ours-r$r"
  "$bin" bench tracking --dataset "$dataset" --frames "$frames" --config "$config" \
    --out "$run.tum" --frames-csv "$run.frames.csv" --json >"$run.json"
  # Our flagged frames: the ones no guess placed (left out of the trajectory).
  awk -F, 'NR > 1 && $3 == "false" { print $1 }' "$run.frames.csv" >"$run.flagged.txt"
  ate "$run.tum"
  if ((open3d)); then
    run="$out/runs/open3d-r$r"
    "$python" scripts/small_gicp_odometry.py open3d --images "$out/images" --out "$run.tum" >"$run.json"
    ate "$run.tum"
  fi
  for v in "${voxel_list[@]}"; do
    run="$out/runs/small_gicp-voxel$v-r$r"
    "$python" scripts/small_gicp_odometry.py track --points "$out/points" --voxel "$v" \
      --threads "$threads" --out "$run.tum" >"$run.json"
    ate "$run.tum"
  done
done
load_after="$(cut -d' ' -f1-3 /proc/loadavg 2>/dev/null || echo unknown)"

context="$(python3 - "$command_line" "$dataset" "$frames" "$threads" "$repeats" "$omp_wait_policy" \
  "$config" "$load_before" "$load_after" "$(git rev-parse --short HEAD 2>/dev/null || echo unknown)" <<'PYTHON'
import datetime, json, os, sys
keys = ["command", "dataset", "frames", "threads", "repeats", "omp_wait_policy", "config",
        "load_before", "load_after", "commit"]
context = dict(zip(keys, sys.argv[1:]))
context["threads"], context["repeats"] = int(context["threads"]), int(context["repeats"])
context["date"] = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
context["cores"] = os.cpu_count()
print(json.dumps(context))
PYTHON
)"
echo "[vs-small_gicp] load (1, 5, 15 min) before $load_before, after $load_after" >&2
python3 scripts/small_gicp_odometry.py report --runs "$out/runs" --gt "$gt" --json "$json" --context "$context" \
  --figures "$out/figures.json" --label "${figures_label:-$(basename "$dataset") $frames}"
echo "[vs-small_gicp] JSON: $json" >&2
record_figures "$bin" "$out/figures.json" "$command_line"
