#!/usr/bin/env bash
# Live ROS 2 input: cameras published over DDS by Cyclone DDS (scripts/ros2/publish_dataset.py,
# stamped with this host's clock), one per agent, and the agents subscribing to them
# (`mac-agent --standalone --dataset ros2:/benchK`, the configuration's pace), all in a network
# namespace of their own (loopback with multicast, standard discovery; nothing leaves the
# machine). Per case and agent: what the agent received, paired, took and dropped (and dropped
# per minute of the camera's run), the transport latency (stamp to arrival), the hand-over
# (arrival to frame, decoding included), the latency from stamp to the frame's pose (median and
# 99th percentile), tracking time, and the agent's CPU seconds per frame taken. Prints a table,
# then JSON. Needs root (network namespaces) and the peers' venv. --figures writes per case the
# frames taken of pairs received, the stamp-to-pose latency of the worse agent and the pairs
# dropped per minute into a docs/figures file through `mac-ego3d bench record-figures`
# (--figures-label: what the run is, default the dataset's folder name and frames).
#
#   scripts/bench_live.sh [--bin-dir target/debug] [--dataset DIR] [--frames 0..300]
#                         [--config configs/7scenes.toml] [--cases compressed@30,raw@10]
#                         [--agents 1] [--out DIR]
#                         [--figures FILE --figures-section HEADING [--figures-label TEXT]
#                          [--machine TEXT]]
#
# With --agents N, N cameras publish the same frames under /bench0.../bench{N-1} at once and
# N agents take them on the same machine (as N robots' agents on one host would).
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
agents=1
out=""
source scripts/figure_options.sh
take_figure_options "$@" || exit 2
set -- "${figure_rest[@]}"
command_line="scripts/bench_live.sh $*"
while (($#)); do
  case "$1" in
    --bin-dir) bin_dir="$2"; shift 2 ;;
    --dataset) dataset="$2"; shift 2 ;;
    --frames) frames="$2"; shift 2 ;;
    --config) config="$2"; shift 2 ;;
    --cases) cases="$2"; shift 2 ;;
    --agents) agents="$2"; shift 2 ;;
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
  echo "[bench-live] $images at $rate Hz, $agents agent(s): $frames of $dataset" >&2
  unshare --net bash -c '
    set -e
    ip link set lo up; ip link set lo multicast on; ip route add 224.0.0.0/4 dev lo
    python="$0"; dataset="$1"; frames="$2"; rate="$3"; images="$4"; dir="$5"; bin_dir="$6"; agents="$7"
    pids=()
    for ((k = 0; k < agents; k++)); do
      "$python" scripts/ros2/publish_dataset.py --dataset "$dataset" --frames "$frames" \
        --namespace "/bench$k" --rate "$rate" --images "$images" --stamps now \
        > "$dir/sent$k.json" &
      pids+=($!)
      /usr/bin/time -f "%U %S" -o "$dir/cpu$k.txt" "$bin_dir/mac-agent" --standalone \
        --config "$dir/config.toml" --agent-id "$k" --dataset "ros2:/bench$k" --renders 0 \
        --out "$dir/agent$k" 2> "$dir/agent$k.log" &
      pids+=($!)
    done
    for pid in "${pids[@]}"; do wait "$pid"; done' \
    "$python" "$dataset" "$frames" "$rate" "$images" "$dir" "$bin_dir" "$agents"
done

python3 - "$out" "$agents" "${figures_label:-$(basename "$dataset") $frames}" "${case_list[@]}" <<'EOF'
import json, sys
out, agents, label, cases = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4:]
rows = []
for case in cases:
    images, rate = case.split("@")
    d = f"{out}/{images}-{rate}"
    for k in range(agents):
        sent = json.load(open(f"{d}/sent{k}.json"))
        m = json.load(open(f"{d}/agent{k}/metrics.json"))
        live = m["live"]
        user, system = (float(x) for x in open(f"{d}/cpu{k}.txt").read().split()[-2:])
        # The publisher waits 1 s after its last frame (best-effort samples in flight).
        seconds = max(1e-9, sent["seconds"] - 1.0)
        rows.append({
            "case": case, "agent": k, "sent": sent["frames"], "sent_hz": sent["frames"] / seconds,
            "received": live["colour_received"],
            "paired": live["paired"], "taken": live["frames"], "dropped": live["dropped"],
            "dropped_while_starting": live["dropped_while_starting"],
            # Per minute of the camera's run after the agent took its first frame.
            "dropped_per_min": (live["dropped"] - live["dropped_while_starting"]) * 60.0
                / max(1e-9, seconds * (1.0 - live["dropped_while_starting"] / max(1, live["paired"]))),
            "unpaired": live["unpaired"], "decode_errors": live["decode_errors"],
            "stamp_to_arrival_ms": live["stamp_to_arrival_ms_median"],
            "handover_ms": live["handover_ms_median"],
            "stamp_to_pose_ms": live.get("stamp_to_pose_ms_median"),
            "stamp_to_pose_ms_p99": live.get("stamp_to_pose_ms_p99"),
            "tracking_ms": m["tracking_ms_median"],
            "fps": m["fps"], "cpu_s_per_frame": (user + system) / max(1, live["frames"]),
            "psnr": m["psnr"],
        })
def f(v, d=1):
    return "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))
print("| case | agent | sent | sent at Hz | received | paired | taken | dropped (starting) | dropped/min running | stamp->arrival ms | hand-over ms | stamp->pose ms (p99) | tracking ms | agent fps | agent CPU s/frame | PSNR dB |")
print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
for r in rows:
    print(f"| {r['case']} | {r['agent']} | {r['sent']} | {f(r['sent_hz'])} | {r['received']} | {r['paired']} | "
          f"{r['taken']} | {r['dropped']} ({r['dropped_while_starting']}) | {f(r['dropped_per_min'])} | "
          f"{f(r['stamp_to_arrival_ms'])} | {f(r['handover_ms'])} | "
          f"{f(r['stamp_to_pose_ms'])} ({f(r['stamp_to_pose_ms_p99'])}) | {f(r['tracking_ms'])} | {f(r['fps'])} | "
          f"{f(r['cpu_s_per_frame'], 3)} | {f(r['psnr'], 2)} |")
print(json.dumps(rows))
# The headline figures (bench record-figures' input): per case, over its agents.
figures = []
for case in cases:
    of_case = [r for r in rows if r["case"] == case]
    images, rate = case.split("@")
    what = f"live ROS 2 input, {len(of_case)} agent(s) ({images}, {rate} Hz, {label})"
    figures.append({"name": f"{what}: frames taken of pairs received, each agent",
                    "value": " / ".join(f"{r['taken']} of {r['paired']}" for r in of_case), "unit": ""})
    latencies = [r for r in of_case if r["stamp_to_pose_ms"] is not None]
    if latencies:
        worse = max(latencies, key=lambda r: r["stamp_to_pose_ms"])
        figures.append({"name": f"{what}: stamp to pose, median (p99), worse agent",
                        "value": f"{worse['stamp_to_pose_ms']:.1f} ({f(worse['stamp_to_pose_ms_p99'])})",
                        "unit": "ms"})
    figures.append({"name": f"{what}: pairs dropped per minute after each agent's first frame",
                    "value": " / ".join(f"{r['dropped_per_min']:.1f}" for r in of_case), "unit": ""})
with open(f"{out}/figures.json", "w", encoding="utf-8") as handle:
    json.dump(figures, handle, indent=2)
EOF
record_figures "$bin_dir/mac-ego3d" "$out/figures.json" "$command_line"
