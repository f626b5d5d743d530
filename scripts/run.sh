#!/usr/bin/env bash
# The README's main command: set-up, build, and the best end-to-end run that exists today on the
# embedded synthetic scene (no download needed). Output goes to ./out (or $1).
#
# Today: write the 3-agent synthetic dataset, read it back through the dataset readers, track
# every agent with G-ICP (frame-to-model, each from its own identity start) and score each
# trajectory against ground truth. It becomes the swarm demo once the agent and consensus
# processes land.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out="${1:-out}"
agents=3
frames=300
cargo build --release --quiet --bin mac-ego3d
bin=target/release/mac-ego3d

"$bin" synth --agents "$agents" --frames "$frames" --out "$out/synthetic" --overwrite
"$bin" dataset info "$out/synthetic"
for ((k = 0; k < agents; k++)); do
  echo "[run] agent $k: G-ICP tracking from identity"
  "$bin" bench tracking --dataset "$out/synthetic/agent_$k" --frames "0..$frames" \
    --config configs/synthetic.toml --out "$out/agent_$k.tum"
  "$bin" eval ate --gt "$out/synthetic/agent_$k/groundtruth_tum.txt" --est "$out/agent_$k.tum"
done
echo "[run] outputs in $out/: synthetic/ (dataset), agent_K.tum (estimated trajectories, TUM)"
