#!/usr/bin/env bash
# The README's test command: set-up, then every test of the workspace.
#
# Real-data tests (named real_data_*) read ../shared (or $MAC_EGO3D_SHARED): 7-Scenes redkitchen
# frames, LPIPS weights, reference trajectories. When that data is present they run. When it is
# missing they are not run and this script lists them and says why; under CI (CI=true) missing data
# is a failure. Extra arguments go to `cargo test` (e.g. a test name filter).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh

# Headless Vulkan (lavapipe, through libwayland) prints "error: XDG_RUNTIME_DIR is invalid or not
# set in the environment." in every process that opens a device when the variable is unset: a
# private, empty runtime folder for the test binaries silences it (the workspace's own binaries
# make one themselves, config::process::provide_runtime_dir).
if [[ "${XDG_RUNTIME_DIR:-}" != /* ]]; then
  XDG_RUNTIME_DIR="$(mktemp -d "${TMPDIR:-/tmp}/mac-ego3d-runtime.XXXXXX")"
  export XDG_RUNTIME_DIR
  trap 'rm -rf "$XDG_RUNTIME_DIR"' EXIT
fi

# The suite is one fresh build, not an edit loop: incremental compilation would only add its
# caches (gigabytes for the optimised workspace crates) to a disk that also holds ~60 test
# binaries. Set CARGO_INCREMENTAL=1 to keep them.
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"

# Formatting first: it fails in seconds, the tests take minutes.
echo "[test] cargo fmt --check"
cargo fmt --all --check
echo "[test] docs/benchmarks.md current figures (scripts/figures.py --check)"
python3 scripts/figures.py --check

# Clippy's lints (warnings are errors) run while the tests build: clippy-driver compiles the
# workspace's own crates in place of rustc (RUSTC_WORKSPACE_WRAPPER, as `cargo clippy` uses it,
# with the same arguments), so the dependency tree is compiled once instead of twice (`cargo
# clippy` type-checks every dependency again: about 10 of a fresh run's minutes on 2 cores), and
# the tests below reuse that build. The lints cover what `cargo clippy --workspace --all-targets`
# covers here (libraries, binaries, tests, examples; the workspace has no benches). A driver that
# does not deny a known lint on a small probe crate falls back to `cargo clippy`. Plain `cargo
# test` afterwards rebuilds the workspace's crates (not the dependencies) without the wrapper.
clippy_denies_warnings() {
  local probe
  probe="$(mktemp -d "${TMPDIR:-/tmp}/mac-ego3d-clippy-probe.XXXXXX")"
  mkdir -p "$probe/src"
  printf '[package]\nname = "probe"\nversion = "0.0.0"\nedition = "2021"\n[workspace]\n' >"$probe/Cargo.toml"
  printf 'fn main() {\n    let v = vec![1];\n    println!("{}", v.iter().count());\n}\n' >"$probe/src/main.rs"
  local denied=1
  CARGO_TARGET_DIR="$probe/target" cargo build --quiet --manifest-path "$probe/Cargo.toml" >/dev/null 2>&1 && denied=0
  rm -rf "$probe"
  ((denied))
}
clippy_driver="$(rustup which clippy-driver 2>/dev/null || command -v clippy-driver || true)"
export RUSTC_WORKSPACE_WRAPPER="$clippy_driver" CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__"
if [[ -x "$clippy_driver" ]] && clippy_denies_warnings; then
  echo "[test] clippy (warnings are errors) while building the tests"
  cargo test --workspace --no-run --quiet
else
  unset RUSTC_WORKSPACE_WRAPPER CLIPPY_ARGS
  echo "[test] cargo clippy (warnings are errors)"
  cargo clippy --workspace --all-targets --quiet -- -D warnings
fi

repo_root=$(pwd)
export MAC_EGO3D_SHARED="${MAC_EGO3D_SHARED:-$repo_root/../shared}"
required=(
  datasets/7scenes-redkitchen/camera-intrinsics.txt
  datasets/7scenes-redkitchen/groundtruth_tum.txt
  datasets/tum-fr1-rpy/groundtruth.txt
  datasets/tum-fr1-rpy/camera-distortion.txt
  weights/lpips/alexnet.npz
  weights/lpips/imgs/ex_ref.png
  reference/tum-trajectories/freiburg1_xyz-groundtruth.txt
)
missing=()
for rel in "${required[@]}"; do
  [[ -e "$MAC_EGO3D_SHARED/$rel" ]] || missing+=("$MAC_EGO3D_SHARED/$rel")
done

# Where set-up added a newer lavapipe beside the system's (scripts/setup.sh), the tests run on the
# newer one; render-core's device tests run again on the system's, whose loop limit and per-lane
# memory accesses some kernels are shaped for (render-core/README.md), so both stay covered.
# Named by target with --workspace (the names are the workspace's only ones), so the features are
# the whole workspace's and nothing is rebuilt (`-p render-core` would rebuild the dependencies).
system_lavapipe_tests() {
  if [[ -f target/vulkan/icd.json && -z "${MAC_EGO3D_ADAPTER:-}" ]]; then
    local system_mesa
    system_mesa="$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null | cut -d. -f1,2)"
    echo "[test] render-core's device tests again on the system's lavapipe (Mesa $system_mesa)"
    MAC_EGO3D_ADAPTER="Mesa $system_mesa" cargo test --workspace --test gpu_forward \
      --test gpu_backward --test training --test map --test device_memory "$@"
  fi
}

if ((${#missing[@]} == 0)); then
  echo "[test] real data found at $MAC_EGO3D_SHARED: running all tests"
  cargo test --workspace "$@"
  system_lavapipe_tests "$@"
  exit 0
fi

if [[ "${CI:-}" == "true" ]]; then
  echo "[test] CI=true but real data is missing:" >&2
  printf '[test]   %s\n' "${missing[@]}" >&2
  echo "[test] set MAC_EGO3D_SHARED to the shared data folder" >&2
  exit 1
fi

cargo test --workspace "$@" -- --skip real_data_
system_lavapipe_tests "$@"
echo
echo "[test] NOT RUN: real-data tests, because this data is missing:"
printf '[test]   %s\n' "${missing[@]}"
echo "[test] (set MAC_EGO3D_SHARED to the folder holding datasets/, weights/, reference/)"
cargo test --workspace -q -- --list 2>/dev/null | sed -n 's/: test$//p' | grep 'real_data_' | sed 's/^/[test]   not run: /' || true
