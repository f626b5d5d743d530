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
set -euo pipefail

log() { printf '[setup] %s\n' "$*" >&2; }

# Debian package -> a file that proves it is installed (cheap check, no apt call when present).
declare -A PACKAGES=(
  [libvulkan1]=/usr/share/doc/libvulkan1
  [mesa-vulkan-drivers]=/usr/share/doc/mesa-vulkan-drivers
  [pkg-config]=/usr/share/doc/pkg-config
  [fonts-dejavu-core]=/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf
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
log "done"
