#!/usr/bin/env bash
# The README's main command: set-up, build, and the swarm demo on the embedded synthetic scene
# (no download needed): one mac-consensus and 3 mac-agent processes, each agent starting at
# identity in its own frame, the consensus finding their frames in one world. Output goes to
# ./out/swarm (or $1); extra arguments go to `mac-ego3d swarm` (scripts/launch_swarm.sh: set-up,
# the one build, then the swarm).
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/swarm}"
shift || true
exec bash scripts/launch_swarm.sh --out "$out" "$@"
