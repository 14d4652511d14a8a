"""The example notebook runs from top to bottom in a Jupyter kernel and shows its images."""

from __future__ import annotations

from pathlib import Path

import nbformat
from nbclient import NotebookClient

NOTEBOOK = Path(__file__).parents[1] / "examples" / "quickstart.ipynb"


def test_quickstart_notebook_executes_and_shows_the_frame_and_plots(tmp_path: Path) -> None:
    nb = nbformat.read(NOTEBOOK, as_version=4)
    NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) == 2  # the rendered frame, then the CoM plots
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "rolled" in text and "CoM estimation error" in text
    rolled = float(text.split("rolled ")[1].split(" m")[0])
    assert rolled > 0.3  # the gait rolls the robot, on estimated states
