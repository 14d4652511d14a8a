"""The Foxglove layout shipped as ``examples/foxglove_layout.json``, built with
foxglove-sdk's own layout classes (``foxglove.layouts``), so that its fields are the
ones Foxglove reads.

    python -m hardware.foxglove_layout examples/foxglove_layout.json

Panels: a 3D panel in the ``world`` frame, following the true red rod (every preset
has one), with the robot's markers (truth and the estimate's ghost), the rod frames of
``/tf`` and the URDF of ``/robot_description`` twice, at the ``truth/`` and the
``estimate/`` frames (layers off at first: the markers already draw the robot); plots
of the CoM error (a user script: the distance between the true and the estimated CoM),
of the true and estimated CoM, and of the estimator's innovations (``/estimate/nis``);
the camera image. A test checks that the file is what this module builds and that
every topic it names is one a bag of the robot has.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from hardware.bag import messages as m
from hardware.bag.scene import ESTIMATE_TREE, GHOST_ALPHA, TRUTH_TREE, WORLD_FRAME, rod_frame

__all__ = ["COM_ERROR_TOPIC", "layout_json"]

log = logging.getLogger(__name__)

COM_ERROR_TOPIC = "/studio_script/com_error"
"""The layout's user script's output: ``error_m``, the CoM error (m)."""
_TRUTH_STATE, _ESTIMATE_STATE = "/ground_truth/state", "/estimate/state"
_CAMERA = "/camera/color/image_raw"

COM_ERROR_SCRIPT = f"""\
// The CoM error (m): the distance between the true and the estimated centre of mass at
// each estimate, from the latest true state (tensegrity_msgs/msg/TensegrityState).
import {{ Input }} from "./types";

type Point = {{ x: number; y: number; z: number }};
type State = {{ center_of_mass: Point }};

export const inputs = ["{_TRUTH_STATE}", "{_ESTIMATE_STATE}"];
export const output = "{COM_ERROR_TOPIC}";

let truth: Point | undefined;

export default function script(
  event: Input<"{_TRUTH_STATE}"> | Input<"{_ESTIMATE_STATE}">,
): {{ error_m: number }} | undefined {{
  const com = (event.message as unknown as State).center_of_mass;
  if (event.topic === "{_TRUTH_STATE}") {{
    truth = com;
    return undefined;
  }}
  if (truth === undefined) {{
    return undefined;
  }}
  return {{ error_m: Math.hypot(com.x - truth.x, com.y - truth.y, com.z - truth.z) }};
}}
"""


def _urdf_layer(fl: Any, tree: str) -> Any:
    """The URDF of ``/robot_description`` drawn at a tree's rod frames (off at first)."""
    return fl.BaseRendererUrdfLayerSettings(
        visible=False, layer_id="foxglove.Urdf", instance_id=f"urdf-{tree}",
        label=f"URDF at {tree}/", source_type="topic", topic=m.DESCRIPTION_TOPIC,
        frame_prefix=f"{tree}/", opacity=1.0 if tree == TRUTH_TREE else GHOST_ALPHA,
    )  # fmt: skip


def _three_d(fl: Any) -> Any:
    """The 3D panel: markers, rod frames, the URDF at each tree (off at first)."""
    urdf = {f"urdf-{tree}": _urdf_layer(fl, tree) for tree in (TRUTH_TREE, ESTIMATE_TREE)}
    grid = fl.BaseRendererGridLayerSettings(
        visible=True, layer_id="foxglove.Grid", instance_id="grid", label="Grid",
        frame_id=WORLD_FRAME, size=10, divisions=40,
    )  # fmt: skip
    return fl.ThreeDeePanel(
        title="The robot: truth and estimate",
        config=fl.ThreeDeeConfig(
            fixed_frame=WORLD_FRAME,
            follow_tf=rod_frame(TRUTH_TREE, "red"),
            follow_mode="follow-position",
            camera_state=fl.ThreeDeeCameraState(distance=2.5, phi=55, theta_offset=45),
            layers={"grid": grid, **urdf},
            topics={m.MARKERS_TOPIC: fl.BaseRendererRosMarkerTopicSettings(visible=True)},
        ),
    )


def _plot(fl: Any, title: str, series: list[tuple[str, str]]) -> Any:
    """A plot of (message path, label) series, against each message's log time."""
    paths = [fl.PlotSeries(value=v, label=label, enabled=True, timestamp_method="receiveTime")
             for v, label in series]  # fmt: skip
    return fl.PlotPanel(title=title, config=fl.PlotConfig(paths=paths, show_legend=True))


def _layout(fl: Any) -> Any:
    com = [
        (f"{topic}.center_of_mass.{axis}", f"{who} {axis}")
        for axis in "xy"
        for topic, who in ((_TRUTH_STATE, "true"), (_ESTIMATE_STATE, "estimated"))
    ]
    plots = [
        _plot(fl, "CoM error (m)", [(f"{COM_ERROR_TOPIC}.error_m", "|true - estimated CoM|")]),
        _plot(fl, "Innovations: NIS per measurement row", [(f"{m.NIS_TOPIC}.data", "NIS")]),
        _plot(fl, "CoM (m): truth and estimate", com),
        fl.ImagePanel(
            title="Camera",
            config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic=_CAMERA)),
        ),
    ]
    column = fl.SplitContainer(
        direction="column", items=[fl.SplitItem(content=panel) for panel in plots]
    )
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=3, content=_three_d(fl)),
                fl.SplitItem(proportion=2, content=column),
            ],
        ),
        user_scripts={"com-error": fl.UserScript(name="CoM error", source_code=COM_ERROR_SCRIPT)},
    )


def layout_json() -> str:
    """The layout as Foxglove's JSON (needs foxglove-sdk), indented, newline-ended."""
    import json

    from hardware.viewer import foxglove_module

    foxglove_module()  # the install hint where it is missing
    import foxglove.layouts as fl

    return json.dumps(json.loads(_layout(fl).to_json()), indent=2) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Write the Foxglove layout.")
    parser.add_argument("out", type=Path, help="the JSON file to write")
    args = parser.parse_args(argv)
    args.out.write_text(layout_json())
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    main()
