#!/usr/bin/env bash
# What the rerun live view costs an agent: standalone runs of one agent on the embedded synthetic
# scene, without and with `--record`, interleaved (so that machine load hits both alike); prints a
# table of fps (median) and .rrd size, and the same as JSON on the last line.
#
#   scripts/bench_live_view.sh [--frames 200] [--repeats 3] [--config configs/synthetic.toml] [--out DIR]
#
# Binaries: the workspace's one build (scripts/build.sh; MAC_EGO3D_PROFILE picks another profile).
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/vulkan_env.sh

frames=200
repeats=3
config=configs/synthetic.toml
out=out/bench_live_view
while (($#)); do
  case "$1" in
    --frames) frames="$2"; shift 2 ;;
    --repeats) repeats="$2"; shift 2 ;;
    --config) config="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    -h | --help) sed -n '2,/^[^#]/p' "$0" | sed -n 's/^# \{0,1\}//p'; exit 0 ;;
    *) echo "[bench] unknown argument: $1" >&2; exit 2 ;;
  esac
done
bin="$(bash scripts/build.sh)/mac-agent"
if [[ "${XDG_RUNTIME_DIR:-}" != /* ]]; then
  XDG_RUNTIME_DIR="$(mktemp -d)"
  export XDG_RUNTIME_DIR
fi
rm -rf "$out"
mkdir -p "$out"

# One run: `run NAME [live-view options]`; prints "fps wall_s".
run() {
  local name="$1"
  shift
  "$bin" --standalone --config "$config" --dataset "synthetic:agents=3,agent=0,frames=$frames" \
    --eval-every 1000 --renders 0 --out "$out/$name" "$@" >"$out/$name.log" 2>&1
  python3 -c 'import json,sys; m=json.load(open(sys.argv[1])); print(m["fps"], m["wall_s"], json.dumps(m.get("live_view")))' \
    "$out/$name/metrics.json"
}

plain=()
recorded=()
sizes=()
drops=()
for ((i = 0; i < repeats; i++)); do
  read -r fps _ _ < <(run "plain_$i")
  plain+=("$fps")
  read -r fps wall stats < <(run "record_$i" --record "$out/rrd_$i")
  recorded+=("$fps")
  size=$(stat -c %s "$out/rrd_$i/agent_0.rrd")
  sizes+=("$size")
  drops+=("$(python3 -c 'import json,sys; print(json.loads(sys.argv[1])["items_dropped"])' "$stats")")
  echo "[bench] pair $i: fps $fps with --record (${plain[-1]} without), .rrd $size bytes in $wall s" >&2
done

python3 - "$frames" "${plain[*]}" "${recorded[*]}" "${sizes[*]}" "${drops[*]}" <<'EOF'
import json, statistics, sys
frames = int(sys.argv[1])
plain, recorded = ([float(v) for v in a.split()] for a in sys.argv[2:4])
sizes = [int(v) for v in sys.argv[4].split()]
drops = [int(v) for v in sys.argv[5].split()]
median = statistics.median
result = {
    "frames": frames,
    "fps_without": median(plain),
    "fps_with_record": median(recorded),
    "fps_runs_without": plain,
    "fps_runs_with_record": recorded,
    "rrd_bytes_median": median(sizes),
    "rrd_bytes_per_frame": median(sizes) / frames,
    "items_dropped": drops,
}
print("| agent | fps (median) | runs | .rrd |")
print("|---|---|---|---|")
print(f"| without --record | {result['fps_without']:.2f} | {', '.join(f'{v:.2f}' for v in plain)} | - |")
print(f"| with --record | {result['fps_with_record']:.2f} | {', '.join(f'{v:.2f}' for v in recorded)} | "
      f"{result['rrd_bytes_median'] / 1e6:.2f} MB ({result['rrd_bytes_per_frame'] / 1e3:.1f} kB/frame) |")
print(json.dumps(result))
EOF
