#!/usr/bin/env bash
# Runs the swarm once per communication interval T_comm and tabulates the figures.
#
#   scripts/bench_tcomm.sh [--values 15,30,60,120,240] [mac-ego3d swarm options] --out DIR
#
# Every option other than --values and --out goes to `mac-ego3d swarm` (--config, --agents,
# --agent DATASET[:FIRST..END], --noise, --frames, ...). Each run lands in DIR/tcomm_K/; the table
# is DIR/tcomm.csv with columns t_comm, ate_joint_rmse_m, psnr, bytes_per_agent_per_s (mean over
# agents), consensus_latency_ms_median, fps_per_agent_mean, loop_closures_accepted, and
# agents_not_linked (agents the consensus never placed in the world: the joint ATE leaves them out).
# A run that fails is reported and left out of the table (its folder keeps the logs).
# DIR/tcomm.png plots every column against T_comm (`mac-ego3d plot tcomm`; empty cells are gaps).
set -euo pipefail
cd "$(dirname "$0")/.."

values=15,30,60,120,240
out=""
passthrough=()
while (($#)); do
  case "$1" in
    --values) values="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    -h | --help) sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) passthrough+=("$1"); shift ;;
  esac
done
[[ -n "$out" ]] || { echo "[tcomm] --out DIR is required" >&2; exit 2; }
# Set-up and the one build, once for every run (scripts/build.sh: the tests' profile).
bash scripts/setup.sh
bin="$(bash scripts/build.sh)"
source scripts/vulkan_env.sh
mkdir -p "$out"
csv="$out/tcomm.csv"
echo "t_comm,ate_joint_rmse_m,psnr,bytes_per_agent_per_s,consensus_latency_ms_median,fps_per_agent_mean,loop_closures_accepted,agents_not_linked" >"$csv"

failed=0
IFS=',' read -ra list <<<"$values"
for t in "${list[@]}"; do
  [[ "$t" =~ ^[0-9]+$ && "$t" -gt 0 ]] || { echo "[tcomm] --values: $t is not a positive integer" >&2; exit 2; }
  run="$out/tcomm_$t"
  echo "[tcomm] T_comm = $t -> $run"
  if ! "$bin/mac-ego3d" swarm "${passthrough[@]}" --tcomm "$t" --out "$run"; then
    echo "[tcomm] the run with T_comm = $t failed; see $run" >&2
    failed=1
    continue
  fi
  python3 - "$run/metrics.json" "$t" >>"$csv" <<'EOF'
import json, sys
m = json.load(open(sys.argv[1]))
def mean(values):
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None
def cell(v):
    return "" if v is None else repr(v)
row = [
    sys.argv[2],
    cell(m.get("ate_joint_rmse_m")),
    cell(m.get("psnr")),
    cell(mean(m.get("bytes_per_agent_per_s", []))),
    cell(m.get("consensus_latency_ms_median")),
    cell(mean(m.get("fps_per_agent", []))),
    cell(m.get("loop_closures_accepted")),
    # The joint ATE covers only the agents placed in the world frame.
    str(len(m.get("agents_not_linked", []))),
]
print(",".join(row))
EOF
done
echo "[tcomm] table: $csv"
column -s, -t <"$csv" 2>/dev/null || cat "$csv"
plot="$out/tcomm.png"
if (($(wc -l <"$csv") > 1)); then
  if "$bin/mac-ego3d" plot tcomm --csv "$csv" --out "$plot"; then
    echo "[tcomm] plots: $plot"
  else
    echo "[tcomm] plotting $csv failed" >&2
    failed=1
  fi
else
  echo "[tcomm] no run finished: nothing to plot" >&2
fi
exit "$failed"
