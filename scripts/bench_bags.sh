#!/usr/bin/env bash
# Bag read throughput: a range of a dataset folder written as rosbag2 bags by the rosbags package
# (scripts/ros2/dataset_to_bag.py) in MCAP and sqlite3 storage, raw and compressed, then read by
# `mac-ego3d bench readers` (frames/s decoded sequentially on one thread, and by the agent's
# prefetching source), beside the folder itself. Prints a table, then JSON. --figures writes
# each source's one-thread throughput into a docs/figures file through `mac-ego3d bench
# record-figures` (--figures-label: what the run is, default the dataset's folder name and frames).
#
#   scripts/bench_bags.sh [--bin target/debug/mac-ego3d] [--dataset DIR] [--frames 0..300]
#                         [--workers 2] [--out DIR]
#                         [--figures FILE --figures-section HEADING [--figures-label TEXT]
#                          [--machine TEXT]]
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/debug/mac-ego3d
dataset="${MAC_EGO3D_SHARED:-../shared}/datasets/7scenes-redkitchen"
frames=0..300
workers=2
out=""
source scripts/figure_options.sh
take_figure_options "$@" || exit 2
set -- "${figure_rest[@]}"
command_line="scripts/bench_bags.sh $*"
while (($#)); do
  case "$1" in
    --bin) bin="$2"; shift 2 ;;
    --dataset) dataset="$2"; shift 2 ;;
    --frames) frames="$2"; shift 2 ;;
    --workers) workers="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    *) echo "unknown option $1" >&2; exit 2 ;;
  esac
done
[[ -x "$bin" ]] || { echo "$bin is missing: build it with scripts/build.sh or cargo build" >&2; exit 1; }
python="$(scripts/peers_venv.sh)" || exit $?
if [[ -z "$out" ]]; then
  out="$(mktemp -d "${TMPDIR:-/tmp}/mac-ego3d-bench-bags.XXXXXX")"
  trap 'rm -rf "$out"' EXIT
fi
source scripts/vulkan_env.sh

results=()
measure() { # name storage images path frames
  local json
  json="$("$bin" bench readers --dataset "$4" --frames "$5" --workers "$workers" --json |
    python3 -c 'import json, sys; print(json.dumps(json.load(sys.stdin)))')"
  local bytes=null
  [[ "$1" == bag ]] && bytes="$(du -sb "$4" | cut -f1)"
  results+=("{\"name\": \"$1\", \"storage\": \"$2\", \"images\": \"$3\", \"bytes\": $bytes, \"readers\": $json}")
}
measure folder folder "as recorded" "$dataset" "$frames"
for storage in mcap sqlite3; do
  for images in raw compressed; do
    bag="$out/bag-$storage-$images"
    rm -rf "$bag"
    "$python" scripts/ros2/dataset_to_bag.py --dataset "$dataset" --frames "$frames" \
      --out "$bag" --storage "$storage" --images "$images" 2>/dev/null
    measure "bag" "$storage" "$images" "$bag" 0..
  done
done

figures_input="$(mktemp "${TMPDIR:-/tmp}/mac-ego3d-bag-figures.XXXXXX")"
printf '%s\n' "${results[@]}" | FRAMES="$frames" FIGURES_INPUT="$figures_input" \
  LABEL="${figures_label:-$(basename "$dataset") $frames}" python3 -c "$(cat <<'PY'
import json, os, sys
rows = [json.loads(line) for line in sys.stdin]
first = rows[0]["readers"]
print(f"bag read throughput, {first['frames']} frames of {first['width']}x{first['height']}")
print(f"{'source':<8} {'storage':<8} {'images':<12} {'MB':>8} {'1 thread fps':>13} {'prefetch fps':>13}")
for r in rows:
    m = r["readers"]
    size = f"{r['bytes'] / 1e6:.1f}" if r["bytes"] else "-"
    print(f"{r['name']:<8} {r['storage']:<8} {r['images']:<12} {size:>8} "
          f"{m['sequential_fps']:>13.1f} {m['prefetch_fps']:>13.1f}")
print(json.dumps({"frames": os.environ["FRAMES"], "rows": rows}, indent=2))
figures = [{
    "name": f"ROS 2 bag read throughput, {os.environ['LABEL']}, "
            + (f"{r['storage'].upper() if r['storage'] == 'mcap' else r['storage']} {r['images']}"
               if r["name"] == "bag" else "the dataset folder")
            + ", 1 thread",
    "value": r["readers"]["sequential_fps"], "decimals": 1, "unit": "frames/s"} for r in rows]
with open(os.environ["FIGURES_INPUT"], "w", encoding="utf-8") as out:
    json.dump(figures, out, indent=2)
PY
)"
record_figures "$bin" "$figures_input" "$command_line"
rm -f "$figures_input"
