#!/usr/bin/env bash
# Runs a swarm with `mac-ego3d swarm`, passing every argument on (all its options:
# `mac-ego3d swarm --help`; one consensus, N agents, Ctrl-C, restarts, metrics.json and
# report.html). Set-up and the workspace's one build (scripts/build.sh) come first, unless
# --bin-dir names ready binaries (a machine without cargo, e.g. scripts/bench_gpu.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
bin=""
previous=""
for arg in "$@"; do
  [[ "$previous" != --bin-dir ]] || bin="$arg"
  [[ "$arg" != --bin-dir=* ]] || bin="${arg#--bin-dir=}"
  previous="$arg"
done
if [[ -z "$bin" ]]; then
  bash scripts/setup.sh
  bin="$(bash scripts/build.sh)"
fi
# The newer lavapipe set-up provisions, for the processes the swarm starts.
source scripts/vulkan_env.sh
exec "$bin/mac-ego3d" swarm "$@"
