#!/usr/bin/env python3
"""Writes a rerun blueprint (.rbl) that lays out a swarm's live view: the world-frame 3D view
(maps, trajectories, keyframes, closures) beside each agent's camera and the consensus's loop
closures and latency, on the `log_time` timeline (the one that shows every process's data together),
following the newest data.

    python3 scripts/live_view_blueprint.py --agents 2 --out swarm.rbl
    rerun swarm.rbl out/swarm_rrd/*.rrd          # or: rerun swarm.rbl, then launch_swarm.sh --viewer

Needs the rerun Python SDK of the viewer's version (`pip install rerun-sdk==0.36.3`); the swarm
itself does not. Without a blueprint the viewer picks a layout of its own.
"""

import argparse

import rerun.blueprint as rrb

# The application id every process of the swarm logs under (live_view::APPLICATION_ID).
APPLICATION_ID = "mac-ego3d"


def blueprint(agents: int) -> rrb.Blueprint:
    cameras = [
        rrb.Spatial2DView(origin=f"/world/agent_{k}/camera", name=f"agent {k} camera")
        for k in range(agents)
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/world", name="swarm map and trajectories (world frame)"),
            rrb.Vertical(
                *cameras,
                rrb.TimeSeriesView(origin="/consensus/closures", name="loop closures"),
                rrb.TimeSeriesView(origin="/consensus/latency_ms", name="consensus latency ms"),
            ),
            column_shares=[3, 1],
        ),
        rrb.TimePanel(timeline="log_time", play_state="following", state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=3, help="agents in the swarm (default 3)")
    parser.add_argument("--out", required=True, help="the .rbl file to write")
    args = parser.parse_args()
    if args.agents < 1:
        parser.error("--agents must be at least 1")
    blueprint(args.agents).save(APPLICATION_ID, args.out)
    print(f"wrote {args.out}: open it with the recordings, e.g. rerun {args.out} DIR/*.rrd")


if __name__ == "__main__":
    main()
