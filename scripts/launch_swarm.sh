#!/usr/bin/env bash
# Launches one mac-consensus and N mac-agent processes (each its own OS process, in parallel),
# waits for all of them, and writes the run's figures.
#
#   scripts/launch_swarm.sh [--config FILE] [--agents N] [--agent DATASET[:FIRST..END]]...
#                           [--tcomm K] [--noise rgb|depth|rgbd] [--frames N]
#                           [--descriptor-weights FILE] [--out DIR]
#
# With no arguments: the embedded synthetic scene, 3 agents (synthetic:agents=3,agent=K).
# --agent repeats, one dataset (and frame range) per agent; agent K is the K-th --agent.
# Ctrl-C is forwarded to every process; each still writes its outputs. A child that dies is
# reported, and every child is reaped (a dead, unreaped child would keep its shared-memory slots).
#
# Output (DIR, default out/swarm): agent_K/ (each agent's own outputs, its frame), agent_K.tum
# (world frame), map.ply (merged world map), consensus.json, metrics.json, *.log.
#
# Not yet: --link-schedule (intermittent links) and report.html; see issue 7.
set -euo pipefail
cd "$(dirname "$0")/.."

config=configs/synthetic.toml
agents=3
tcomm=""
noise=""
frames=200
out=out/swarm
weights="${MAC_EGO3D_SHARED:-../shared}/weights/lpips/alexnet.npz"
specs=()
profile="${MAC_EGO3D_PROFILE:-release}"

usage() { sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//'; }
while (($#)); do
  case "$1" in
    --config) config="$2"; shift 2 ;;
    --agents) agents="$2"; shift 2 ;;
    --agent) specs+=("$2"); shift 2 ;;
    --tcomm) tcomm="$2"; shift 2 ;;
    --noise) noise="$2"; shift 2 ;;
    --frames) frames="$2"; shift 2 ;;
    --descriptor-weights) weights="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --link-schedule)
      echo "[swarm] --link-schedule is not implemented yet (issue 7)" >&2; exit 2 ;;
    -h | --help) usage; exit 0 ;;
    *) echo "[swarm] unknown argument: $1" >&2; usage >&2; exit 2 ;;
  esac
done
if ((${#specs[@]})); then
  agents=${#specs[@]}
fi
[[ -f "$config" ]] || { echo "[swarm] --config $config: no such file" >&2; exit 2; }

bash scripts/setup.sh
if [[ "$profile" == release ]]; then
  cargo build --release --quiet -p mac-agent -p mac-consensus -p mac-ego3d --bins
else
  cargo build --quiet -p mac-agent -p mac-consensus -p mac-ego3d --bins
fi
bin="target/$profile"

# Per-run config: the given one, with T_comm and noise overridden when asked.
mkdir -p "$out"
run_config="$out/config.toml"
cp "$config" "$run_config"
if [[ -n "$tcomm" ]]; then
  python3 - "$run_config" "$tcomm" <<'EOF'
import re, sys
path, tcomm = sys.argv[1], sys.argv[2]
text = open(path).read()
if re.search(r'(?m)^\s*t_comm\s*=', text):
    text = re.sub(r'(?m)^(\s*t_comm\s*=\s*)\d+', lambda m: m.group(1) + tcomm, text)
elif re.search(r'(?m)^\[consensus\]', text):
    text = re.sub(r'(?m)^\[consensus\]\s*$', '[consensus]\nt_comm = ' + tcomm, text, count=1)
else:
    text += '\n[consensus]\nt_comm = ' + tcomm + '\n'
open(path, 'w').write(text)
EOF
fi
if [[ -n "$noise" ]]; then
  case "$noise" in rgb | depth | rgbd) ;; *) echo "[swarm] --noise $noise: expected rgb, depth or rgbd" >&2; exit 2 ;; esac
  printf '\n[noise]\ntarget = "%s"\n' "$noise" >>"$run_config"
fi
weight_args=()
eval_args=()
if [[ -f "$weights" ]]; then
  weight_args=(--descriptor-weights "$weights")
  # The same AlexNet file carries LPIPS's layers.
  eval_args=(--lpips-weights "$weights")
else
  echo "[swarm] no descriptor weights at $weights: agents use the classical descriptor" >&2
fi

# One namespace per run, so two runs on one host never share services.
namespace="mac$$"
pids=()
names=()
cleanup() {
  for pid in "${pids[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
}
trap 'echo "[swarm] interrupted: stopping every process (each writes its outputs)" >&2; cleanup' INT TERM

"$bin/mac-consensus" --config "$run_config" --out "$out" --agents "$agents" \
  --namespace "$namespace" >"$out/consensus.log" 2>&1 &
pids+=($!)
names+=(consensus)
for ((k = 0; k < agents; k++)); do
  if ((${#specs[@]})); then
    spec="${specs[$k]}"
    # DATASET[:FIRST..END]; a synthetic spec has colons of its own, so only a trailing range
    # is split off.
    if [[ "$spec" =~ ^(.*):([0-9]*\.\.[0-9]*)$ ]]; then
      dataset="${BASH_REMATCH[1]}"
      range="${BASH_REMATCH[2]}"
    else
      dataset="$spec"
      range=".."
    fi
  else
    dataset="synthetic:agents=$agents,agent=$k,frames=$frames"
    range=".."
  fi
  "$bin/mac-agent" --config "$run_config" --dataset "$dataset" --frames "$range" --agent-id "$k" \
    --namespace "$namespace" --out "$out/agent_$k" "${weight_args[@]}" \
    >"$out/agent_$k.log" 2>&1 &
  pids+=($!)
  names+=("agent $k")
  echo "[swarm] agent $k: $dataset ($range), log $out/agent_$k.log"
done

# Reap every child; report the ones that failed.
failed=0
for i in "${!pids[@]}"; do
  status=0
  while true; do
    wait "${pids[$i]}" && status=0 || status=$?
    # 128+ from `wait` itself when a trapped signal interrupted it: wait again.
    if ((status > 128)) && kill -0 "${pids[$i]}" 2>/dev/null; then continue; fi
    break
  done
  if ((status != 0)); then
    echo "[swarm] ${names[$i]} exited with status $status; see its log in $out" >&2
    failed=1
  fi
done

"$bin/mac-ego3d" eval swarm --dir "$out" "${eval_args[@]}" || failed=1
exit "$failed"
