#!/usr/bin/env bash
# The README's main command: set-up, build, and the best end-to-end run that exists today on the
# embedded synthetic scene (no download needed). Output goes to ./out (or $1).
#
# Today: write the 3-agent synthetic dataset, read it back through the dataset readers, and
# measure reader throughput on it.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out="${1:-out}"
cargo build --release --quiet --bin mac-ego3d
bin=target/release/mac-ego3d

"$bin" synth --agents 3 --frames 300 --out "$out/synthetic"
"$bin" dataset info "$out/synthetic"
"$bin" bench readers --dataset "$out/synthetic/agent_0" --frames 0..300
echo "[run] outputs in $out/"
