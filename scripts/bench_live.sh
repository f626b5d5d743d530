#!/usr/bin/env bash
# Live ROS 2 input: a camera published over DDS by Cyclone DDS (scripts/ros2/publish_dataset.py,
# stamped with this host's clock) and one agent subscribing to it (`mac-agent --standalone
# --dataset ros2:/bench`, the configuration's pace), both in a network namespace of their own
# (loopback with multicast, standard discovery; nothing leaves the machine). Per case: what the
# agent received, paired, took and dropped, the transport latency (stamp to arrival), the
# hand-over (arrival to frame, decoding included), tracking time, and the agent's CPU seconds per
# frame taken. Prints a table, then JSON. Needs root (network namespaces) and the peers' venv.
#
#   scripts/bench_live.sh [--bin-dir target/debug] [--dataset DIR] [--frames 0..300]
#                         [--config configs/7scenes.toml] [--cases compressed@30,raw@10] [--out DIR]
#
# A case is IMAGES@HZ: compressed (JPEG colour, compressedDepth PNG) or raw (rgb8, 16UC1). The
# publisher serialises raw images in Python at about 30 ms per megabyte, so raw cannot reach
# 30 Hz here; that is the publisher's limit, not the agent's.
set -euo pipefail
cd "$(dirname "$0")/.."
bin_dir=target/debug
dataset="${MAC_EGO3D_SHARED:-../shared}/datasets/7scenes-redkitchen"
frames=0..300
config=configs/7scenes.toml
cases=compressed@30,raw@10
out=""
while (($#)); do
  case "$1" in
    --bin-dir) bin_dir="$2"; shift 2 ;;
    --dataset) dataset="$2"; shift 2 ;;
    --frames) frames="$2"; shift 2 ;;
    --config) config="$2"; shift 2 ;;
    --cases) cases="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    *) echo "unknown option $1" >&2; exit 2 ;;
  esac
done
[[ -x "$bin_dir/mac-agent" ]] || { echo "$bin_dir/mac-agent is missing: cargo build -p mac-agent" >&2; exit 1; }
(($(id -u) == 0)) || { echo "the live benchmark needs root (a network namespace)" >&2; exit 2; }
python="$(scripts/peers_venv.sh)" || exit $?
if [[ -z "$out" ]]; then
  out="$(mktemp -d "${TMPDIR:-/tmp}/mac-ego3d-bench-live.XXXXXX")"
  trap 'rm -rf "$out"' EXIT
fi
mkdir -p "$out"
source scripts/vulkan_env.sh

IFS=, read -ra case_list <<<"$cases"
for case in "${case_list[@]}"; do
  images="${case%@*}"
  rate="${case#*@}"
  dir="$out/$images-$rate"
  rm -rf "$dir"
  mkdir -p "$dir"
  topics=()
  if [[ "$images" == compressed ]]; then
    topics=(colour_topic=/camera/camera/color/image_raw/compressed
      depth_topic=/camera/camera/aligned_depth_to_color/image_raw/compressedDepth)
  fi
  # The configuration with the case's topics and a short idle end.
  python3 - "$config" "$dir/config.toml" "${topics[@]}" <<'EOF'
import sys
source, target, *topics = sys.argv[1:]
text = open(source).read()
lines = ["", "[ros2]", "idle_timeout_s = 4.0"] + [f'{k} = "{v}"' for k, v in (t.split("=", 1) for t in topics)]
if "\n[ros2]" in text:
    sys.exit(f"{source} has a [ros2] section: give a configuration without one")
open(target, "w").write(text + "\n".join(lines) + "\n")
EOF
  echo "[bench-live] $images at $rate Hz: $frames of $dataset" >&2
  unshare --net bash -c '
    set -e
    ip link set lo up; ip link set lo multicast on; ip route add 224.0.0.0/4 dev lo
    "$0" scripts/ros2/publish_dataset.py --dataset "$1" --frames "$2" --namespace /bench \
      --rate "$3" --images "$4" --stamps now > "$5/sent.json" &
    /usr/bin/time -f "%U %S" -o "$5/cpu.txt" "$6/mac-agent" --standalone --config "$5/config.toml" \
      --dataset ros2:/bench --renders 0 --out "$5/agent" 2> "$5/agent.log"
    wait' "$python" "$dataset" "$frames" "$rate" "$images" "$dir" "$bin_dir"
done

python3 - "$out" "${case_list[@]}" <<'EOF'
import json, sys
out, cases = sys.argv[1], sys.argv[2:]
rows = []
for case in cases:
    images, rate = case.split("@")
    d = f"{out}/{images}-{rate}"
    sent = json.load(open(f"{d}/sent.json"))
    m = json.load(open(f"{d}/agent/metrics.json"))
    live = m["live"]
    user, system = (float(x) for x in open(f"{d}/cpu.txt").read().split()[-2:])
    rows.append({
        # The publisher waits 1 s after its last frame (best-effort samples in flight).
        "case": case, "sent": sent["frames"], "sent_hz": sent["frames"] / max(1e-9, sent["seconds"] - 1.0),
        "received": live["colour_received"],
        "paired": live["paired"], "taken": live["frames"], "dropped": live["dropped"],
        "unpaired": live["unpaired"], "decode_errors": live["decode_errors"],
        "stamp_to_arrival_ms": live["stamp_to_arrival_ms_median"],
        "handover_ms": live["handover_ms_median"], "tracking_ms": m["tracking_ms_median"],
        "fps": m["fps"], "cpu_s_per_frame": (user + system) / max(1, live["frames"]),
        "psnr": m["psnr"],
    })
def f(v, d=1):
    return "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))
print("| case | sent | sent at Hz | received | paired | taken | dropped | stamp->arrival ms | hand-over ms | tracking ms | agent fps | agent CPU s/frame | PSNR dB |")
print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
for r in rows:
    print(f"| {r['case']} | {r['sent']} | {f(r['sent_hz'])} | {r['received']} | {r['paired']} | {r['taken']} | {r['dropped']} | "
          f"{f(r['stamp_to_arrival_ms'])} | {f(r['handover_ms'])} | {f(r['tracking_ms'])} | {f(r['fps'])} | "
          f"{f(r['cpu_s_per_frame'], 3)} | {f(r['psnr'], 2)} |")
print(json.dumps(rows))
EOF
