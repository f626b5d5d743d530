#!/usr/bin/env bash
# Tracking speed and accuracy side by side: ours (`mac-ego3d bench tracking`) and small_gicp's
# frame-to-model odometry (scripts/small_gicp_odometry.py), on the same points, in one run.
#
#   scripts/bench_vs_small_gicp.sh [--frames 0..300] [--threads 2] [--voxels 0.05,0.02]
#       [--repeats 5] [--omp-wait-policy passive] [--dataset DIR] [--gt TUM] [--config FILE]
#       [--out DIR] [--json FILE]
#
# Same input: a first, untimed run of ours writes every frame's points as our tracker
# back-projected them (`bench tracking --dump-points`: same depth frames, pixel stride, truncation
# and intrinsics, from --config, default configs/7scenes.toml) and small_gicp tracks those. Same
# threads: RAYON_NUM_THREADS and OMP_NUM_THREADS = --threads, and small_gicp's num_threads too.
# small_gicp's OpenMP threads wait passively by default (--omp-wait-policy, OMP_WAIT_POLICY), as
# rayon's idle workers sleep: on a machine shared with other work, spinning OpenMP threads wait
# for a descheduled peer and small_gicp measures far slower than it is (docs/benchmarks.md).
# Then --repeats rounds, each running ours and small_gicp at every --voxels size (its
# GaussianVoxelMap voxel, m) back to back, so load changes spread over all of them. Both
# trajectories are scored by the same code, `mac-ego3d eval ate` against --gt (default:
# DIR/groundtruth_tum.txt of the dataset).
# Prints one table (per tracker: medians over the repeats of ms/frame median and p90, ATE RMSE,
# ours / small_gicp ms ratio, stage medians) and writes it as JSON to --json (default
# OUT/summary.json). Every run's files stay in --out (default: a new folder under $TMPDIR).
#
# small_gicp and numpy come from PyPI, as pinned wheels whose sha256 is checked against the
# hashes below (pip --require-hashes), into a virtual environment outside the repository:
# ${XDG_CACHE_HOME:-~/.cache}/mac-ego3d/venv-small-gicp (reused while the pins are unchanged).
# Without PyPI the script says so and exits 3. Dataset: $MAC_EGO3D_SHARED (default ../shared).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/vulkan_env.sh
repo="$(pwd)"

# Pinned wheels: CPython 3.10-3.13 on manylinux x86_64 and aarch64 (`pip download` + `pip hash`).
readonly REQUIREMENTS='small_gicp==1.0.1 \
    --hash=sha256:0a68868802b1a37dd945beb9b941678a294ab2a775e3d4887bb6d010c11ca544 \
    --hash=sha256:85fc0df28db88538eb70122a04c521608ba694f74078024b8cdedd1ef936158c \
    --hash=sha256:8cd292278b16401ce76e4d485bc854522bf047e21496fa684b8ff9a80510610a \
    --hash=sha256:a0570d1d97e8b5b72c8e7302d2aefe740036ad790e4931af81ed3951b5b0956f \
    --hash=sha256:8b870571667a9b7c003de4579234f7f00917a80bb254d6ccc498c0a4ca30e819 \
    --hash=sha256:cb08400204c468acf5145503f5ab8c0bd495871d335975638916e64b32cf8452 \
    --hash=sha256:d6eee0ed36852a931457918461cec144fb42499691b9bb02f2c2404915f8ab7b \
    --hash=sha256:60f717ee4b570ef515efe748f430a4a0e6b4518f2d1af8a9353f889dadd90e9a
numpy==2.2.6 \
    --hash=sha256:efd28d4e9cd7d7a8d39074a4d44c63eda73401580c5c76acda2ce969e0a38e83 \
    --hash=sha256:fc7b73d02efb0e18c000e9ad8b83480dfcd5dfd11065997ed4c6747470ae8915 \
    --hash=sha256:b64d8d4d17135e00c8e346e0a738deb17e754230d7e0810ac5012750bbd85a5a \
    --hash=sha256:ba10f8411898fc418a521833e014a77d3ca01c15b0c6cdcce6a0d2897e6dbbdf \
    --hash=sha256:f2618db89be1b4e05f7a1a847a9c1c0abd63e63a1607d892dd54668dd92faf87 \
    --hash=sha256:fd83c01228a688733f1ded5201c678f0c53ecc1006ffbc404db9f7a899ac6249 \
    --hash=sha256:f92729c95468a2f4f15e9bb94c432a9229d0d50de67304399627a943201baa2f \
    --hash=sha256:1bc23a79bfabc5d056d106f9befb8d50c31ced2fbc70eedb8155aec74a45798f
'

fail() { echo "[vs-small_gicp] $1" >&2; exit "${2:-1}"; }
usage() { sed -n '2,27p' "$0" | sed 's/^# \{0,1\}//'; }

shared="${MAC_EGO3D_SHARED:-../shared}"
frames=0..300
threads=2
voxels=0.05,0.02
repeats=5
omp_wait_policy=passive
dataset="$shared/datasets/7scenes-redkitchen"
gt=""
config=configs/7scenes.toml
out=""
json=""
command_line="scripts/bench_vs_small_gicp.sh $*"
while (($#)); do
  case "$1" in
    --frames) frames="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --voxels) voxels="$2"; shift 2 ;;
    --repeats) repeats="$2"; shift 2 ;;
    --omp-wait-policy) omp_wait_policy="$2"; shift 2 ;;
    --dataset) dataset="$2"; shift 2 ;;
    --gt) gt="$2"; shift 2 ;;
    --config) config="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --json) json="$2"; shift 2 ;;
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
gt="${gt:-$dataset/groundtruth_tum.txt}"
[[ -f "$gt" ]] || fail "--gt $gt: no such file (the ground truth both trajectories are scored against)" 2
[[ -f "$config" ]] || fail "--config $config: no such file" 2
command -v python3 >/dev/null 2>&1 || fail "python3 is required (with venv and pip) but is not on PATH"
[[ -n "$out" ]] || out="$(mktemp -d "${TMPDIR:-/tmp}/bench_vs_small_gicp.XXXXXX")"
mkdir -p "$out/runs"
out="$(cd "$out" && pwd)"
json="${json:-$out/summary.json}"

# --- small_gicp in its own virtual environment, outside the repository -------------------------
venv="${XDG_CACHE_HOME:-$HOME/.cache}/mac-ego3d/venv-small-gicp"
case "$(realpath -m "$venv")/" in
  "$repo"/*) fail "the virtual environment $venv would be inside the repository; set XDG_CACHE_HOME elsewhere" 2 ;;
esac
pins="$(printf '%s' "$REQUIREMENTS" | sha256sum | cut -d' ' -f1)"
if [[ "$(cat "$venv/.pins-sha256" 2>/dev/null)" != "$pins" ]] ||
  ! "$venv/bin/python" -c 'import numpy, small_gicp' 2>/dev/null; then
  echo "[vs-small_gicp] installing the pinned small_gicp and numpy into $venv" >&2
  rm -rf "$venv"
  python3 -m venv "$venv" || fail "could not create a virtual environment (python3 -m venv $venv)"
  printf '%s' "$REQUIREMENTS" >"$venv/requirements.txt"
  # --only-binary: the hashes are of the wheels; --no-deps: every package is pinned here.
  if ! "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --retries 1 \
    --timeout 30 --no-deps --only-binary :all: --require-hashes -r "$venv/requirements.txt"; then
    rm -rf "$venv"
    fail "could not install small_gicp 1.0.1 and numpy 2.2.6 from PyPI: PyPI is unreachable, or \
there is no pinned wheel for $(python3 -c 'import platform; print("CPython", platform.python_version(), platform.machine())') \
(pinned: CPython 3.10-3.13, manylinux x86_64/aarch64); pip's message is above" 3
  fi
  echo "$pins" >"$venv/.pins-sha256"
fi
python="$venv/bin/python"

# --- our binary ------------------------------------------------------------------------------
echo "[vs-small_gicp] building mac-ego3d (release; up to date unless the sources changed)" >&2
cargo build --release --quiet -p mac-ego3d --bin mac-ego3d
bin="${CARGO_TARGET_DIR:-target}/release/mac-ego3d"

export RAYON_NUM_THREADS="$threads" OMP_NUM_THREADS="$threads" OMP_WAIT_POLICY="$omp_wait_policy"
load_before="$(cut -d' ' -f1-3 /proc/loadavg 2>/dev/null || echo unknown)"
echo "[vs-small_gicp] $dataset frames $frames, $threads threads, $repeats repeats; load $load_before; files in $out" >&2

# Untimed: our points for small_gicp (the file writes would disturb the timings).
"$bin" bench tracking --dataset "$dataset" --frames "$frames" --config "$config" \
  --dump-points "$out/points" --json >"$out/dump-run.json"

ate() { "$bin" eval ate --gt "$gt" --est "$1" --json >"${1%.tum}.ate.json"; }
for ((r = 1; r <= repeats; r++)); do
  echo "[vs-small_gicp] round $r/$repeats" >&2
  run="$out/runs/ours-r$r"
  "$bin" bench tracking --dataset "$dataset" --frames "$frames" --config "$config" \
    --out "$run.tum" --json >"$run.json"
  ate "$run.tum"
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
python3 scripts/small_gicp_odometry.py report --runs "$out/runs" --json "$json" --context "$context"
echo "[vs-small_gicp] JSON: $json" >&2
