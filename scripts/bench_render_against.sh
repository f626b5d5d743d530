#!/usr/bin/env bash
# The renderer's speed against an earlier revision, side by side on this machine:
# `mac-ego3d bench render` of REV and of the working tree take turns, round by round, on each
# Vulkan driver set below. Prints the medians over the rounds and the ratio tree / REV as a
# table and writes them as JSON.
#
#   scripts/bench_render_against.sh --rev REV [--rounds 3] [--gaussians 100000]
#       [--sizes 320x240,640x480] [--repeats 9] [--forward-only] [--out DIR]
#       [--rev-bin FILE] [--bin FILE]
#
# Binaries: REV's mac-ego3d is built in a git worktree of REV under target/bench-against/
# with its own cargo target folder there, kept for the next run (the first build of a
# revision takes as long as a fresh build); the working tree's by `cargo build --release
# --bin mac-ego3d`. --rev-bin and --bin take built binaries instead (nothing is built; --rev
# then only names REV in the report).
# Drivers: "system" is the machine's own Vulkan drivers, what every revision before set-up
# fetched a newer lavapipe ran on. "provisioned" is only the lavapipe set-up keeps in
# target/vulkan/icd.json (Debian 12), measured when that file is there. Both binaries see only
# the set's drivers (the Vulkan loader's VK_DRIVER_FILES), so a revision that cannot choose
# an adapter runs on the same one. With both sets, the report adds REV on "system" against the
# tree on "provisioned": what a user of REV's set-up had against what set-up gives now.
# Output: OUT/summary.json and each run's `bench render --json` in OUT/runs (default OUT:
# target/bench-against/runs/<date-time>).
set -euo pipefail
cd "$(dirname "$0")/.."

fail() { echo "[bench-against] $1" >&2; exit "${2:-1}"; }
usage() { sed -n '2,24p' "$0" | sed 's/^# \{0,1\}//'; }

rev=""
rev_bin=""
tree_bin=""
rounds=3
gaussians=100000
sizes=320x240,640x480
repeats=9
forward_only=""
out=""
while [[ $# -gt 0 ]]; do
  case "$1" in
    --rev) rev="$2"; shift 2 ;;
    --rev-bin) rev_bin="$2"; shift 2 ;;
    --bin) tree_bin="$2"; shift 2 ;;
    --rounds) rounds="$2"; shift 2 ;;
    --gaussians) gaussians="$2"; shift 2 ;;
    --sizes) sizes="$2"; shift 2 ;;
    --repeats) repeats="$2"; shift 2 ;;
    --forward-only) forward_only=--forward-only; shift ;;
    --out) out="$2"; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; fail "unknown argument: $1" 2 ;;
  esac
done
[[ -n "$rev" ]] || fail "--rev is required (the revision to compare with)" 2
[[ "$rounds" =~ ^[1-9][0-9]*$ ]] || fail "--rounds takes a positive count, not '$rounds'" 2
[[ "$repeats" =~ ^[1-9][0-9]*$ ]] || fail "--repeats takes a positive count, not '$repeats'" 2
work="$(pwd)/target/bench-against"
out="${out:-$work/runs/$(date +%Y%m%d-%H%M%S)}"
mkdir -p "$out/runs" "$work"

# REV's binary: built once per commit in its own worktree and target folder.
if [[ -z "$rev_bin" ]]; then
  commit="$(git rev-parse --verify "$rev^{commit}" 2>/dev/null)" \
    || fail "--rev $rev is not a commit of this repository" 2
  rev_bin="$work/bin-$commit/mac-ego3d"
  if [[ ! -x "$rev_bin" ]]; then
    source="$work/src-$commit"
    git worktree prune
    [[ -d "$source" ]] || git worktree add --detach "$source" "$commit" >/dev/null \
      || fail "could not check out $rev into $source"
    echo "[bench-against] building $rev ($commit) in $source (a fresh build the first time)"
    (cd "$source" && CARGO_TARGET_DIR="$work/target" cargo build --release --bin mac-ego3d) \
      || fail "building $rev failed (see cargo's messages above)"
    mkdir -p "$(dirname "$rev_bin")"
    cp "$work/target/release/mac-ego3d" "$rev_bin"
  fi
fi
# The tree's binary, copied so a build during the rounds cannot change it.
if [[ -z "$tree_bin" ]]; then
  echo "[bench-against] building the working tree"
  cargo build --release --bin mac-ego3d || fail "building the working tree failed"
  mkdir -p "$out/bin"
  cp target/release/mac-ego3d "$out/bin/mac-ego3d"
  tree_bin="$out/bin/mac-ego3d"
fi
for binary in "$rev_bin" "$tree_bin"; do
  [[ -x "$binary" ]] || fail "$binary is not an executable" 2
done

drivers=(system)
provisioned_icd="$(pwd)/target/vulkan/icd.json"
[[ -f "$provisioned_icd" ]] && drivers+=(provisioned)

# One `bench render` of binary $2 on driver set $3 into $4.
bench() {
  local name="$1" binary="$2" driver="$3" json="$4"
  local -a driver_env=(env -u VK_ADD_DRIVER_FILES -u VK_DRIVER_FILES -u MAC_EGO3D_ADAPTER)
  [[ "$driver" == provisioned ]] && driver_env+=(VK_DRIVER_FILES="$provisioned_icd")
  if ! "${driver_env[@]}" "$binary" bench render --gaussians "$gaussians" --sizes "$sizes" \
      --repeats "$repeats" $forward_only --json > "$json" 2> "${json%.json}.log"; then
    echo "[bench-against] $name on $driver failed (${json%.json}.log); the report leaves it out"
    rm -f "$json"
  fi
}

for round in $(seq 1 "$rounds"); do
  for driver in "${drivers[@]}"; do
    echo "[bench-against] round $round/$rounds, $driver drivers"
    bench rev "$rev_bin" "$driver" "$out/runs/rev.$driver.$round.json"
    bench tree "$tree_bin" "$driver" "$out/runs/tree.$driver.$round.json"
  done
done

python3 - "$out" "$rev" "$rounds" "$repeats" <<'PY'
import glob, json, os, statistics, sys

out, rev, rounds, repeats = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
METRICS = ("forward_ms", "iteration_ms")
runs = {}  # (binary, driver) -> list of bench render reports
for path in sorted(glob.glob(os.path.join(out, "runs", "*.json"))):
    binary, driver, _ = os.path.basename(path).split(".", 2)
    runs.setdefault((binary, driver), []).append(json.load(open(path)))
if not runs:
    sys.exit("[bench-against] no run succeeded: nothing to report")

def medians(binary, driver):
    """Per case (gaussians, width, height): each metric's median over the rounds and its runs."""
    cases = {}
    for report in runs.get((binary, driver), []):
        for case in report["cases"]:
            key = (case["gaussians"], case["width"], case["height"])
            for metric in METRICS:
                if case.get(metric) is not None:
                    cases.setdefault(key, {}).setdefault(metric, []).append(case[metric])
    return {key: {metric: {"median": statistics.median(values), "runs": values}
                  for metric, values in per_metric.items()}
            for key, per_metric in cases.items()}

def adapter(binary, driver):
    reports = runs.get((binary, driver), [])
    return reports[0].get("adapter", "") if reports else ""

def compare(label, before, after):
    rows = []
    for key in sorted(set(before) | set(after)):
        row = {"comparison": label, "gaussians": key[0], "width": key[1], "height": key[2]}
        for metric in METRICS:
            old = before.get(key, {}).get(metric)
            new = after.get(key, {}).get(metric)
            row[metric] = {
                "rev": old, "tree": new,
                "ratio": new["median"] / old["median"] if old and new and old["median"] > 0 else None,
            }
        rows.append(row)
    return rows

drivers = sorted({driver for _, driver in runs}, key=lambda d: d != "system")
rows = []
for driver in drivers:
    rows += compare(driver, medians("rev", driver), medians("tree", driver))
if "system" in drivers and "provisioned" in drivers:
    rows += compare("rev system -> tree provisioned", medians("rev", "system"),
                    medians("tree", "provisioned"))

summary = {
    "rev": rev, "rounds": rounds, "repeats": repeats,
    "adapters": {f"{binary} {driver}": adapter(binary, driver) for binary, driver in sorted(runs)},
    "rows": rows,
}
with open(os.path.join(out, "summary.json"), "w") as f:
    json.dump(summary, f, indent=1)

def cell(value):
    return "-" if value is None else f"{value:.1f}"

print(f"\nbench render, {rev} (rev) against the working tree (tree): medians of {rounds} rounds "
      f"of {repeats} repeats, ms")
for name, text in summary["adapters"].items():
    print(f"  {name}: {text}")
print("| drivers | Gaussians | size | forward rev | forward tree | ratio "
      "| iteration rev | iteration tree | ratio |")
print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
for row in rows:
    cells = []
    for metric in METRICS:
        m = row[metric]
        cells += [cell(m["rev"] and m["rev"]["median"]), cell(m["tree"] and m["tree"]["median"]),
                  "-" if m["ratio"] is None else f"{m['ratio']:.2f}"]
    print(f"| {row['comparison']} | {row['gaussians']} | {row['width']}x{row['height']} | "
          + " | ".join(cells) + " |")
print(f"\nJSON: {os.path.join(out, 'summary.json')}")
PY
