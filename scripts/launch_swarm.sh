#!/usr/bin/env bash
# Launches one mac-consensus and N mac-agent processes (each its own OS process, in parallel),
# waits for all of them, and writes the run's figures.
#
#   scripts/launch_swarm.sh [--config FILE] [--agents N] [--agent DATASET[:FIRST..END[:STEP]]]...
#                           [--tcomm K] [--link-schedule FILE] [--noise rgb|depth|rgbd]
#                           [--frames N] [--descriptor-weights FILE] [--out DIR]
#                           [--set KEY=VALUE]...
#                           [--no-restart-consensus]
#                           [--transport iceoryx2|zenoh] [--insecure-plain-tcp] [--bandwidth KB_PER_S]
#                           [--viewer [ADDR]] [--record DIR] [--bin-dir DIR]
#
# With no arguments: the embedded synthetic scene, 3 agents (synthetic:agents=3,agent=K).
# --agent repeats, one dataset (and frame range) per agent; agent K is the K-th --agent.
# --set KEY=VALUE overrides one configuration key for every process of the run (dotted path, as
# `mac-ego3d config --set`: `--set consensus.t_comm=30`); repeatable, applied after --tcomm and
# --noise, checked before anything starts.
# --link-schedule FILE simulates intermittent links: per agent, the time windows in which it can
# talk to the consensus; what it publishes meanwhile is queued and delivered at reconnect (the
# format is documented in agent/src/link_schedule.rs). The file is checked before anything starts.
# Ctrl-C (or SIGTERM) stops the run in order: the agents finish their frame and hand over their
# outputs, then the consensus writes the world trajectories and map from them (it waits up to
# STOP_WAIT_S for the agents' goodbyes). The children run in sessions of their own, so a terminal's
# Ctrl-C reaches this script only and the order holds; a second Ctrl-C kills everything at once
# (outputs may then be incomplete). A child that dies is reported at once, and every child is reaped (a dead, unreaped child would keep its shared-memory
# slots); when agents failed, the consensus is stopped once the others are done.
# A consensus that dies (killed, crashed) is started again on the run folder, up to
# CONSENSUS_RESTARTS_MAX times: it resumes from its store (DIR/consensus.redb), the agents
# publish again what it lost, and the outputs are those of a run without the crash.
# --no-restart-consensus reports its death instead. Each launch is a new run: the consensus starts
# with a new run id and --fresh, so an older run's store in DIR is moved aside, never resumed.
# --transport zenoh (root only) runs the consensus and each agent as a simulated host of its own
# (scripts/simulated_host.sh: own mount namespace, private /dev/shm and iceoryx2 root, own
# mac-bridge), all joined by zenoh over TLS on 127.0.0.1 with mutual authentication: the run makes
# its own swarm CA and a certificate per host in DIR/certs (`mac-bridge certs`).
# --insecure-plain-tcp joins them over plain TCP instead (no authentication; warned about).
# metrics.json then counts each agent's bytes on the network. The default, iceoryx2, runs
# everything on this host's shared memory.
# --bandwidth KB_PER_S (with --transport zenoh) caps what each agent sends to other hosts
# (`--set network.agent_kb_per_s=KB_PER_S`): its host's bridge compresses keyframe images and
# Gaussian patches and defers them, and never drops one (docs/method.md, Across hosts).
# On a terminal, one line shows the progress: frames, keyframes, link state, closures.
# --viewer [ADDR] streams every process to a rerun viewer (ADDR: HOST:PORT, default
# 127.0.0.1:9876): when `rerun` is on PATH and nothing listens there yet, one is started; else the
# processes connect to ADDR (a viewer started later still gets what they log from then on).
# --record DIR writes DIR/consensus.rrd and DIR/agent_K.rrd (one per process; a restarted
# consensus writes consensus-2.rrd, ...); `rerun DIR/*.rrd` opens them together. Every process
# logs under one recording id, the run id. Neither ever slows the run (see the live_view crate).
#
# The AlexNet weights (global descriptor, LPIPS) are the cached ones scripts/setup.sh fetches
# ($MAC_EGO3D_WEIGHTS, else ~/.cache/mac-ego3d/weights/lpips/alexnet.npz) unless
# --descriptor-weights names a file; without any, the agents use the classical descriptor.
#
# Binaries: CARGO_TARGET_DIR (default target)/MAC_EGO3D_PROFILE (default release), built first
# (MAC_EGO3D_BUILD_AS_TESTS=1: as `cargo test --workspace` builds them; for test harnesses).
# --bin-dir DIR runs the binaries in DIR as they are, with no build and no set-up step: for a
# machine without cargo that the binaries were copied to (its Vulkan driver and the weights are
# then the caller's to provide).
#
# Output (DIR, default out/swarm): agent_K/ (each agent's own outputs, its frame), agent_K.tum
# (world frame), map.ply (merged world map), consensus.json, metrics.json, report.html, *.log.
set -euo pipefail
shopt -s checkwinsize
cd "$(dirname "$0")/.."

config=configs/synthetic.toml
agents=3
tcomm=""
noise=""
frames=200
out=out/swarm
weights=""
specs=()
sets=()
link_schedule=""
restart_consensus=1
profile="${MAC_EGO3D_PROFILE:-release}"
# --- transport (cross-host bridge) ---
transport=iceoryx2
insecure_plain_tcp=0
bandwidth=""
# --- end transport ---
viewer=""
record=""
bin_dir=""

# The header above, up to its first line that is not a comment.
usage() { sed -n '2,/^[^#]/p' "$0" | sed -n 's/^# \{0,1\}//p'; }
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
    --link-schedule) link_schedule="$2"; shift 2 ;;
    --set) sets+=("$2"); shift 2 ;;
    --no-restart-consensus) restart_consensus=0; shift ;;
    --transport) transport="$2"; shift 2 ;;
    --insecure-plain-tcp) insecure_plain_tcp=1; shift ;;
    --bandwidth) bandwidth="$2"; sets+=("network.agent_kb_per_s=$2"); shift 2 ;;
    --viewer)
      # The address is optional: the next argument is it unless it is another option.
      if (($# > 1)) && [[ "$2" != --* ]]; then viewer="$2"; shift 2; else viewer=127.0.0.1:9876; shift; fi ;;
    --record) record="$2"; shift 2 ;;
    --bin-dir) bin_dir="$2"; shift 2 ;;
    -h | --help) usage; exit 0 ;;
    *) echo "[swarm] unknown argument: $1" >&2; usage >&2; exit 2 ;;
  esac
done
if ((${#specs[@]})); then
  agents=${#specs[@]}
fi
[[ -f "$config" ]] || { echo "[swarm] --config $config: no such file" >&2; exit 2; }
[[ -z "$link_schedule" || -f "$link_schedule" ]] ||
  { echo "[swarm] --link-schedule $link_schedule: no such file" >&2; exit 2; }
# --- transport (cross-host bridge) ---
case "$transport" in
  iceoryx2) ;;
  zenoh) (($(id -u) == 0)) || { echo "[swarm] --transport zenoh simulates hosts with mount namespaces: run as root" >&2; exit 2; } ;;
  *) echo "[swarm] --transport $transport: expected iceoryx2 or zenoh" >&2; exit 2 ;;
esac
((!insecure_plain_tcp)) || [[ "$transport" == zenoh ]] ||
  { echo "[swarm] --insecure-plain-tcp is for --transport zenoh" >&2; exit 2; }
[[ -z "$bandwidth" || "$transport" == zenoh ]] ||
  { echo "[swarm] --bandwidth caps traffic between hosts: give --transport zenoh too (on one host the swarm shares memory)" >&2; exit 2; }
# --- end transport ---

# Mesa's Vulkan loader path (libwayland, probing for a display) prints "error: XDG_RUNTIME_DIR
# is invalid or not set in the environment." in every process when the variable is unset, as on a
# headless machine, in a container or over plain ssh. Nothing here opens a window: a private,
# empty runtime folder (mode 700, removed at exit) silences it and hides no other message.
if [[ "${XDG_RUNTIME_DIR:-}" != /* ]]; then
  XDG_RUNTIME_DIR="$(mktemp -d "${TMPDIR:-/tmp}/mac-ego3d-runtime.XXXXXX")"
  export XDG_RUNTIME_DIR
  trap 'rm -rf "$XDG_RUNTIME_DIR"' EXIT
fi

if [[ -n "$bin_dir" ]]; then
  for binary in mac-agent mac-consensus mac-ego3d; do
    [[ -x "$bin_dir/$binary" ]] || { echo "[swarm] --bin-dir: $bin_dir/$binary is missing" >&2; exit 2; }
  done
  [[ "$transport" != zenoh || -x "$bin_dir/mac-bridge" ]] ||
    { echo "[swarm] --bin-dir: $bin_dir/mac-bridge is missing (--transport zenoh needs it)" >&2; exit 2; }
  bin="$bin_dir"
else
  bash scripts/setup.sh
  # Binaries where cargo puts them (CARGO_TARGET_DIR, when set, moves the whole target folder).
  bin="${CARGO_TARGET_DIR:-target}/$profile"
  build_args=(-p mac-agent -p mac-consensus -p mac-ego3d --bins)
  [[ "$profile" == release ]] && build_args+=(--release)
  # Started from inside `cargo test`, this script inherits the variables cargo sets for a test
  # (CARGO_MANIFEST_DIR, CARGO_PKG_*, ...); a build script that watches one (ring's watches
  # CARGO_MANIFEST_DIR) would make the build below rebuild it and everything above it.
  for var in $(compgen -e); do
    case "$var" in
      CARGO_MANIFEST_* | CARGO_PKG_* | CARGO_CRATE_NAME | CARGO_BIN_* | CARGO_PRIMARY_PACKAGE | \
        CARGO_TARGET_TMPDIR | CARGO_RUSTC_CURRENT_DIR | OUT_DIR) unset "$var" ;;
    esac
  done
  # MAC_EGO3D_BUILD_AS_TESTS=1: build as `cargo test --workspace` does (every binary, the whole
  # workspace's features), which is nothing to do right after it: test harnesses set it. `cargo
  # build -p ...` alone resolves the features of shared dependencies for those packages only, which
  # differ from the whole workspace's, and would rebuild most of the dependency tree (minutes).
  if [[ "${MAC_EGO3D_BUILD_AS_TESTS:-}" == 1 ]]; then
    test_build_args=(--workspace --no-run --quiet)
    [[ "$profile" == release ]] && test_build_args+=(--release)
    cargo test "${test_build_args[@]}"
  else
    if [[ -x "$bin/mac-agent" && -x "$bin/mac-consensus" && -x "$bin/mac-ego3d" ]]; then
      echo "[swarm] building mac-agent, mac-consensus, mac-ego3d ($profile; up to date unless the sources changed)" >&2
    else
      echo "[swarm] building mac-agent, mac-consensus, mac-ego3d ($profile; the first build takes several minutes, progress below)" >&2
    fi
    cargo build "${build_args[@]}"
    # --- transport (cross-host bridge) ---
    # Built on its own: in one invocation with the others, cargo would unify the features of their
    # shared dependencies with zenoh's and rebuild them all.
    if [[ "$transport" == zenoh ]]; then
      bridge_args=(-p mac-bridge)
      [[ "$profile" == release ]] && bridge_args+=(--release)
      cargo build "${bridge_args[@]}"
    fi
    # --- end transport ---
  fi
fi

# The newer lavapipe set-up provisions, for the processes started below.
source scripts/vulkan_env.sh

# Per-run config: the given one, with T_comm and noise overridden when asked, resolved and
# validated by mac-ego3d (every key listed, so the run folder says exactly what ran).
mkdir -p "$out"
run_config="$out/config.toml"
overrides=()
[[ -n "$tcomm" ]] && overrides+=(--set "consensus.t_comm=$tcomm")
if [[ -n "$noise" ]]; then
  case "$noise" in rgb | depth | rgbd) ;; *) echo "[swarm] --noise $noise: expected rgb, depth or rgbd" >&2; exit 2 ;; esac
  overrides+=(--set "noise.target=$noise")
fi
for pair in "${sets[@]}"; do
  overrides+=(--set "$pair")
done
# Written beside and renamed: the given file may be this very path (a rerun into one folder).
"$bin/mac-ego3d" config --config "$config" "${overrides[@]}" --out "$run_config.new" ||
  { echo "[swarm] the configuration is refused (above)" >&2; exit 2; }
mv "$run_config.new" "$run_config"
# Without --descriptor-weights, every process uses the default weights (alexnet::weights) and
# says in its log when there are none; setup.sh has already said so on the screen.
weight_args=()
eval_args=()
if [[ -n "$weights" ]]; then
  [[ -f "$weights" ]] || { echo "[swarm] --descriptor-weights $weights: no such file" >&2; exit 2; }
  weight_args=(--descriptor-weights "$weights")
  # The same AlexNet file carries LPIPS's layers.
  eval_args=(--lpips-weights "$weights")
fi

schedule_args=()
if [[ -n "$link_schedule" ]]; then
  # Kept with the outputs, like config.toml; checked once here rather than failing in every agent.
  run_schedule="$out/link_schedule.toml"
  [[ "$link_schedule" -ef "$run_schedule" ]] || cp "$link_schedule" "$run_schedule"
  "$bin/mac-agent" --link-schedule "$run_schedule" --check-link-schedule "$agents" | sed 's/^/[swarm] /'
  schedule_args=(--link-schedule "$run_schedule")
fi

# How long an interrupted consensus waits for the agents' final maps and goodbyes.
STOP_WAIT_S=60
# Children run in sessions of their own (setsid), so the Ctrl-C a terminal sends to its foreground
# process group reaches this script only, which stops them in order (see the header).
detach=()
command -v setsid >/dev/null 2>&1 && detach=(setsid)

# One namespace per run, so two runs on one host never share services.
namespace="mac$$"
# The run's identity in the consensus store: a restarted consensus resumes this run only.
run_id="$namespace-$(date +%s)"

# The rerun live view: every process under one recording id, the run id.
live_args=()
if [[ -n "$viewer" ]]; then
  viewer_host="${viewer%:*}"
  viewer_port="${viewer##*:}"
  if [[ "$viewer" != *://* ]] && ! (exec 3<>"/dev/tcp/$viewer_host/$viewer_port") 2>/dev/null; then
    if command -v rerun >/dev/null 2>&1 && [[ "$viewer_host" == 127.0.0.1 || "$viewer_host" == localhost ]]; then
      echo "[swarm] starting the rerun viewer (port $viewer_port; log $out/rerun.log)"
      "${detach[@]}" rerun --port "$viewer_port" >"$out/rerun.log" 2>&1 &
      for _ in $(seq 50); do
        (exec 3<>"/dev/tcp/$viewer_host/$viewer_port") 2>/dev/null && break
        sleep 0.2
      done
    else
      echo "[swarm] no viewer listens at $viewer (and no \`rerun\` on PATH to start one): the processes connect to it and send once a viewer is there; what they cannot send in time is dropped"
    fi
  else
    echo "[swarm] live view: connecting to the rerun viewer at $viewer"
  fi
  live_args+=(--viewer "$viewer")
fi
if [[ -n "$record" ]]; then
  mkdir -p "$record"
  # Recordings of an earlier run into this folder would open beside this run's.
  rm -f "$record"/consensus*.rrd "$record"/agent_*.rrd
  live_args+=(--record "$record")
  echo "[swarm] recording the live view to $record/*.rrd (open with: rerun $record/*.rrd)"
fi
((${#live_args[@]} == 0)) || live_args+=(--recording-id "$run_id")
# Restarts of a dead consensus at most (a consensus that cannot start fails fast each time).
CONSENSUS_RESTARTS_MAX=10
consensus_restarts=0
pids=()
names=()
interrupts=0
# First interrupt: agents get SIGTERM (finish the frame, write outputs, say goodbye), the consensus
# SIGINT (it asks agents it still hears from to stop, waits for their goodbyes, then writes). A
# second interrupt kills every child.
on_interrupt() {
  clear_progress
  interrupts=$((interrupts + 1))
  if ((interrupts == 1)); then
    echo "[swarm] interrupted: the agents finish their frame and hand over their outputs, then the consensus writes the world outputs (Ctrl-C again to stop everything now)" >&2
    for pid in "${pids[@]:1}"; do kill -TERM "$pid" 2>/dev/null || true; done
    kill -INT "${pids[0]}" 2>/dev/null || true
  else
    echo "[swarm] interrupted again: killing every process (outputs may be incomplete)" >&2
    for pid in "${pids[@]}"; do kill -KILL "$pid" 2>/dev/null || true; done
  fi
}
show_progress=0
[[ -t 1 ]] && show_progress=1
# Erases the progress line before a message is printed.
clear_progress() { if ((show_progress)); then printf '\r\033[K'; fi; }
trap on_interrupt INT TERM

# Progress files of the previous run in this folder would show stale figures.
rm -f "$out"/agent_*/progress.json "$out/consensus_progress.json"

# --- transport (cross-host bridge) ---
# With zenoh, every process below runs on a simulated host of its own: `on_host NAME BRIDGE_ARGS
# -- PROGRAM` (the consensus host listens on a free port of 127.0.0.1, agent hosts connect).
consensus_host=()
if [[ "$transport" == zenoh ]]; then
  zenoh_port="$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
  # Each simulated host's link credentials: `bridge_security HOST` sets `security`.
  if ((insecure_plain_tcp)); then
    echo "[swarm] WARNING: --insecure-plain-tcp: the simulated hosts talk plain TCP without authentication" >&2
    zenoh_scheme=tcp
    bridge_security() { security=(--insecure-plain-tcp); }
  else
    zenoh_scheme=tls
    # A new CA per run: the certificates of an earlier run in this folder are replaced.
    rm -rf "$out/certs"
    host_specs=(--host consensus=127.0.0.1)
    for ((k = 0; k < agents; k++)); do host_specs+=(--host "agent$k"); done
    "$bin/mac-bridge" certs --out "$out/certs" "${host_specs[@]}" 2>>"$out/certs.log" ||
      { echo "[swarm] making the run's certificates failed; see $out/certs.log" >&2; exit 1; }
    bridge_security() { security=(--certificates "$out/certs" --host "$1"); }
  fi
  bridge_security consensus
  consensus_host=(scripts/simulated_host.sh "$bin/mac-bridge" --role consumers --namespace "$namespace"
    --agents "$agents" --listen "$zenoh_scheme/127.0.0.1:$zenoh_port" "${security[@]}"
    --report "$out/bridge_consensus.json" --)
  echo "[swarm] transport zenoh: simulated hosts joined over $zenoh_scheme/127.0.0.1:$zenoh_port; bridge logs in $out/*.log"
fi
# The command prefix that runs agent K on its own simulated host (empty with iceoryx2).
agent_host_of() {
  agent_host=()
  [[ "$transport" == zenoh ]] || return 0
  bridge_security "agent$1"
  agent_host=(scripts/simulated_host.sh "$bin/mac-bridge" --role agents --namespace "$namespace"
    --agents "$agents" --local-agent "$1" --connect "$zenoh_scheme/127.0.0.1:$zenoh_port"
    "${security[@]}" --report "$out/bridge_agent_$1.json" --config "$run_config" --)
}
# --- end transport ---
# Starts the consensus (in the background; its pid in $!): the first start is a new run
# (--fresh), a restart resumes it from the store. Its log is appended to across restarts.
start_consensus() {
  local fresh=()
  ((consensus_restarts > 0)) || fresh=(--fresh)
  "${detach[@]}" "${consensus_host[@]}" "$bin/mac-consensus" --config "$run_config" --out "$out" --agents "$agents" \
    --namespace "$namespace" --run-id "$run_id" "${fresh[@]}" --stop-agents "$STOP_WAIT_S" "${live_args[@]}" \
    >>"$out/consensus.log" 2>&1 &
}
: >"$out/consensus.log"
start_consensus
pids+=($!)
names+=(consensus)
# The agents share this host's cores: each tracks with its share of them (a worker pool larger
# than its share waits at every parallel step for a worker that another process holds). A
# RAYON_NUM_THREADS set by the caller wins.
cores="$(nproc)"
agent_threads="${RAYON_NUM_THREADS:-$((cores / agents > 0 ? cores / agents : 1))}"
echo "[swarm] $agents agents on $cores cores: $agent_threads tracking threads each"
for ((k = 0; k < agents; k++)); do
  if ((${#specs[@]})); then
    spec="${specs[$k]}"
    # DATASET[:FIRST..END[:STEP]] (datasets::DatasetSpec); a synthetic spec has colons of its
    # own, so only a trailing range is split off.
    if [[ "$spec" =~ ^(.*):([0-9]*\.\.[0-9]*(:[0-9]+)?)$ ]]; then
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
  agent_host_of "$k"
  "${detach[@]}" "${agent_host[@]}" env RAYON_NUM_THREADS="$agent_threads" "$bin/mac-agent" --config "$run_config" --dataset "$dataset" --frames "$range" --agent-id "$k" \
    --namespace "$namespace" --out "$out/agent_$k" "${weight_args[@]}" "${schedule_args[@]}" "${live_args[@]}" \
    >"$out/agent_$k.log" 2>&1 &
  pids+=($!)
  names+=("agent $k")
  echo "[swarm] agent $k: $dataset ($range), log $out/agent_$k.log"
done

# Reads a flat JSON object from FILE into `json` (values unquoted); leaves it empty when the file
# is missing or incomplete. Builtins only: this runs every second.
declare -A json=()
read_json() {
  json=()
  [[ -r "$1" ]] || return 0
  local text="" pair='"([a-z_]+)":[[:space:]]*("[^"]*"|[-+.eE0-9]+|true|false|null)'
  IFS= read -r -d '' text <"$1" || true
  [[ "$text" =~ \}[[:space:]]*$ ]] || return 0
  while [[ "$text" =~ $pair ]]; do
    json[${BASH_REMATCH[1]}]=${BASH_REMATCH[2]//\"/}
    text=${text#*"${BASH_REMATCH[0]}"}
  done
}

# One line: per agent frames (of the total), keyframes, link state; the consensus's keyframes,
# closures and pending alignments once it writes consensus_progress.json. When the line is wider
# than the terminal, the agents' part is abbreviated (0:120/200,8kf).
progress_line() {
  local full=() short=() k text brief
  for ((k = 0; k < agents; k++)); do
    read_json "$out/agent_$k/progress.json"
    if [[ -z "${json[frames_done]:-}" ]]; then
      full+=("agent $k: starting")
      short+=("$k:starting")
      continue
    fi
    text="agent $k: ${json[frames_done]}"
    brief="$k:${json[frames_done]}"
    if [[ "${json[frames_total]:-null}" != null ]]; then
      text+="/${json[frames_total]}"
      brief+="/${json[frames_total]}"
    fi
    text+=" f, ${json[keyframes]:-0} kf"
    brief+=",${json[keyframes]:-0}kf"
    if [[ "${json[link_up]:-}" == false ]]; then
      text+=", link down (${json[queued_keyframes]:-0} queued)"
      brief+=",down"
    fi
    case "${json[stage]:-}" in
      finishing) text+=", finishing" brief+=",fin" ;;
      done) text+=", done" brief+=",done" ;;
    esac
    full+=("$text")
    short+=("$brief")
  done
  local consensus=""
  read_json "$out/consensus_progress.json"
  if [[ -n "${json[keyframes]:-}" ]]; then
    consensus=" | consensus: ${json[keyframes]} kf, ${json[closures_verified]:-0} closures"
    [[ -z "${json[inter_agent_closures]:-}" ]] || consensus+=" (${json[inter_agent_closures]} inter-agent)"
    [[ "${json[pending_alignments]:-0}" == 0 ]] || consensus+=", ${json[pending_alignments]} aligning"
  fi
  local line="${full[0]}" part
  for part in "${full[@]:1}"; do line+=" | $part"; done
  line+="$consensus"
  # checkwinsize (set at the top) sets COLUMNS after external commands.
  local width=$((${COLUMNS:-80} - 1))
  if ((${#line} > width)); then
    line="agents ${short[*]}$consensus"
  fi
  printf '\r%s\033[K' "${line:0:width}"
}

# Wait for every child, reaping each as it ends and reporting a failure at once; poll once a
# second (a trapped Ctrl-C interrupts the wait at once, so forwarding is never delayed).
declare -A exit_status=()
failed=0
agents_failed=0
stopping_consensus=0
while ((${#exit_status[@]} < ${#pids[@]})); do
  for i in "${!pids[@]}"; do
    [[ -z "${exit_status[$i]:-}" ]] || continue
    # bash reaps ended children in the background and keeps their status for `wait`.
    if kill -0 "${pids[$i]}" 2>/dev/null; then continue; fi
    status=0
    wait "${pids[$i]}" || status=$?
    if ((i == 0 && status != 0 && restart_consensus && interrupts == 0 &&
      consensus_restarts < CONSENSUS_RESTARTS_MAX)); then
      consensus_restarts=$((consensus_restarts + 1))
      clear_progress
      echo "[swarm] the consensus exited with status $status: starting it again on its store (restart $consensus_restarts of at most $CONSENSUS_RESTARTS_MAX; log $out/consensus.log)" >&2
      start_consensus
      pids[0]=$!
      continue
    fi
    exit_status[$i]=$status
    if ((status != 0)); then
      clear_progress
      echo "[swarm] ${names[$i]} exited with status $status; see its log in $out" >&2
      failed=1
      ((i == 0)) || agents_failed=1
    fi
  done
  # The consensus waits for every agent's goodbye; a failed agent may never send one.
  if ((agents_failed && !stopping_consensus && ${#exit_status[@]} == ${#pids[@]} - 1)) &&
    [[ -z "${exit_status[0]:-}" ]]; then
    clear_progress
    echo "[swarm] every agent has ended, some failed: stopping the consensus (it writes its outputs)" >&2
    kill -TERM "${pids[0]}" 2>/dev/null || true
    stopping_consensus=1
  fi
  ((${#exit_status[@]} < ${#pids[@]})) || break
  ((show_progress)) && progress_line
  sleep 1 &
  wait $! 2>/dev/null || true
done
if ((show_progress)); then
  progress_line
  printf '\n'
fi

"$bin/mac-ego3d" eval swarm --dir "$out" "${eval_args[@]}" || failed=1
# --- transport (cross-host bridge) ---
# metrics.json says which transport carried the run and, over zenoh, each agent's traffic on the
# network as its host's bridge counted it (relayed bytes, both directions, and the mean rate).
if [[ -f "$out/metrics.json" ]]; then
  python3 - "$out" "$transport" "$agents" <<'PY' || failed=1
import json, os, sys
out, transport, agents = sys.argv[1], sys.argv[2], int(sys.argv[3])
path = os.path.join(out, "metrics.json")
metrics = json.load(open(path))
metrics["transport"] = transport
if transport == "zenoh":
    network = {}
    for k in range(agents):
        report_path = os.path.join(out, f"bridge_agent_{k}.json")
        if not os.path.exists(report_path):
            network[str(k)] = None
            continue
        report = json.load(open(report_path))
        traffic = report["agents"].get(str(k), {})
        sent, received = traffic.get("bytes_to_network", 0), traffic.get("bytes_from_network", 0)
        elapsed = report["elapsed_s"]
        network[str(k)] = {
            "bytes_to_network": sent,
            "bytes_from_network": received,
            "elapsed_s": elapsed,
            "kb_per_s_to_network": sent / 1000 / elapsed if elapsed > 0 else None,
            # What the bandwidth budget did: bytes as published and as sent, messages per
            # encoding, Gaussians left out, deferral.
            "budget": report.get("budget", {}).get(str(k)),
        }
    metrics["network_bytes_per_agent"] = network
json.dump(metrics, open(path, "w"), indent=2)
PY
fi
# --- end transport ---
if [[ -f "$out/report.html" ]]; then
  # Absolute paths: this script ran from the repository root, the user may be elsewhere.
  dir="$(cd "$out" && pwd)"
  echo
  echo "[swarm] next:"
  echo "[swarm]   the report: $dir/report.html (open it in a browser, e.g. xdg-open $dir/report.html)"
  echo "[swarm]   the merged map: $dir/map.ply (3DGS PLY: any Gaussian-splat viewer, e.g. SuperSplat)"
  echo "[swarm]   trajectories: $dir/agent_K.tum (world frame; e.g. evo_traj tum $dir/agent_*.tum --plot)"
  echo "[swarm]   what each process logged: $dir/*.log"
fi
exit "$failed"
