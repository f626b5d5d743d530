#!/usr/bin/env bash
# The workspace's one build: every binary, in the profile `cargo test --workspace` uses for them
# (dev: optimised, see Cargo.toml), so scripts/run.sh and scripts/test.sh compile the dependency
# tree once between them. MAC_EGO3D_PROFILE=release builds the release profile instead (a tree
# of its own). Prints the binaries' folder on stdout; cargo's progress goes to stderr.
set -euo pipefail
cd "$(dirname "$0")/.."
profile="${MAC_EGO3D_PROFILE:-dev}"
cargo build --workspace --bins --profile "$profile" >&2
folder="$profile"
[[ "$profile" != dev ]] || folder=debug
echo "${CARGO_TARGET_DIR:-$(pwd)/target}/$folder"
