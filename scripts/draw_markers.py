"""Draw a bag's robot markers with matplotlib, headless (the picture of docs/recordings.md).

    python scripts/draw_markers.py BAG OUT.png [--frame -1]

Reads ``/tensegrity/markers`` (visualization_msgs/MarkerArray) of a bag written by
``tensegrity-gym record`` and draws one frame of it (the last by default) from above and
from the side: the true rods as thick lines in their colours, the estimate's as faint
ones (the ghost), endcaps as dots, cables coloured by tension (grey: slack); the goal
and the UWB anchors, up to metres away, are left out. It is a drawing of the markers a
ROS viewer shows, not a screenshot of one.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from rosbags.rosbag2 import Reader

from hardware.bag import messages as m

log = logging.getLogger(__name__)

_SPHERE, _CYLINDER, _LINE_LIST = 2, 3, 5
_VIEWS = (("from above", 0, 1), ("from the side", 0, 2))
"""(title, horizontal axis, vertical axis) of each panel: x, y, z = 0, 1, 2."""


def _frames(bag: Path) -> list[Any]:
    """Every MarkerArray of the bag, in log-time order."""
    store = m.typestore()
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == m.MARKERS_TOPIC]
        if not conns:
            raise SystemExit(f"{bag}: no {m.MARKERS_TOPIC} (recorded with --no-markers?)")
        return [store.deserialize_cdr(raw, m.MARKER_ARRAY) for _, _, raw in reader.messages(conns)]


def _rod_ends(marker: Any) -> tuple[list[float], list[float]]:
    """The two end points of a cylinder marker (its body z axis, ``scale.z`` long)."""
    q, p, half = marker.pose.orientation, marker.pose.position, 0.5 * marker.scale.z
    # the body z axis of the quaternion (x, y, z, w)
    axis = (
        2 * (q.x * q.z + q.w * q.y),
        2 * (q.y * q.z - q.w * q.x),
        1 - 2 * (q.x * q.x + q.y * q.y),
    )
    centre = (p.x, p.y, p.z)
    return (
        [c - half * a for c, a in zip(centre, axis, strict=True)],
        [c + half * a for c, a in zip(centre, axis, strict=True)],
    )


def _draw(ax: Any, markers: list[Any], h: int, v: int) -> None:
    for mk in markers:
        rgba = (mk.color.r, mk.color.g, mk.color.b, mk.color.a)
        xyz = (mk.pose.position.x, mk.pose.position.y, mk.pose.position.z)
        if mk.type == _CYLINDER and mk.ns.endswith("/rods"):
            a, b = _rod_ends(mk)
            ax.plot([a[h], b[h]], [a[v], b[v]], color=rgba, lw=6 if rgba[3] > 0.9 else 3,
                    solid_capstyle="round", zorder=3)  # fmt: skip
        elif mk.type == _SPHERE:
            ax.scatter([xyz[h]], [xyz[v]], s=30, color=rgba, zorder=4)
        elif mk.type == _LINE_LIST:
            for k in range(0, len(mk.points), 2):
                p, q, c = mk.points[k], mk.points[k + 1], mk.colors[k]
                ends = [(p.x, p.y, p.z), (q.x, q.y, q.z)]
                ax.plot([e[h] for e in ends], [e[v] for e in ends], lw=1.2, zorder=2,
                        color=(c.r, c.g, c.b, c.a))  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frame", type=int, default=-1, help="which MarkerArray (-1: last)")
    args = parser.parse_args(argv)
    frame = _frames(args.bag)[args.frame]
    robot = [mk for mk in frame.markers if mk.action == 0 and mk.ns not in ("anchors", "goal")]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4), layout="constrained")
    for ax, (title, h, v) in zip(axes, _VIEWS, strict=True):
        _draw(ax, robot, h, v)
        ax.set_title(f"/tensegrity/markers {title}")
        ax.set_xlabel("xyz"[h] + " (m)")
        ax.set_ylabel("xyz"[v] + " (m)")
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    fig.suptitle("truth (solid) and estimate (faint); cables yellow to red by tension, grey slack")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    main()
