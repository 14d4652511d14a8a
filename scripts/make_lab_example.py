"""Write ``examples/lab/``: a lab's UWB ranges file and its id map, in the lab's own ids
and units, from SUPERball carried through a 10 x 15 m room (tensegrity_gym.sim.carried).

    python scripts/make_lab_example.py [SECONDS]
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np

from estimation.uwb_calibration.rounds import sample_rows
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.sim.carried import carried_recording

OUT = Path(__file__).resolve().parents[1] / "examples" / "lab"
NODE_IDS = [f"0x{0x0A + k:02X}" for k in range(12)]  # the lab's module ids
ANCHOR_IDS = [str(101 + a) for a in range(8)]
EPOCH_MS = 1_465_000_000_000  # the lab's clock: ms since 1970

IDS = """\
# The lab's ids -> the description's (superball): endcaps by name or index,
# anchors by index in sensors.uwb.anchors. Units of the ranges file.
nodes:
{nodes}
anchors:
{anchors}
units: {{time: ms, range: mm}}
"""


def main(seconds: float) -> None:
    d = load_robot("superball")
    rec = carried_recording(d, np.random.default_rng(2016), seconds=seconds)
    t, i, j, m, _ = sample_rows(rec.uwb)
    node, other = np.minimum(i, j), np.maximum(i, j) - d.n_nodes
    OUT.mkdir(parents=True, exist_ok=True)
    with (OUT / "ranges.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "node", "anchor", "range"])
        for row in zip(t, node, other, m, strict=True):
            w.writerow([EPOCH_MS + round(1e3 * row[0]), NODE_IDS[row[1]], ANCHOR_IDS[row[2]],
                        round(1e3 * row[3])])  # fmt: skip
    nodes = "\n".join(f'  "{lab}": {d.nodes[k].name}' for k, lab in enumerate(NODE_IDS))
    anchors = "\n".join(f'  "{lab}": {a}' for a, lab in enumerate(ANCHOR_IDS))
    (OUT / "ids.yaml").write_text(IDS.format(nodes=nodes, anchors=anchors))


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 90.0)
