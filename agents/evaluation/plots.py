"""Plots for people: CoM paths from above and errors over time (matplotlib, headless)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pathlib import Path

    import numpy as np
    from numpy.typing import NDArray

__all__ = ["plot_com_paths", "plot_errors", "pyplot"]


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # headless: files only, no window
    import matplotlib.pyplot as plt

    return plt


def plot_com_paths(
    true_path: NDArray[np.float64] | None,
    est_path: NDArray[np.float64],
    file: Path,
    title: str,
) -> None:
    """The true (if known) and estimated CoM seen from above; paths (T, 3) in metres."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 5))
    ref = true_path if true_path is not None else est_path
    if true_path is not None:
        ax.plot(true_path[:, 0], true_path[:, 1], "-", color="tab:blue", label="true CoM")
    ax.plot(est_path[:, 0], est_path[:, 1], "--", color="tab:orange", label="estimated CoM")
    ax.plot(*ref[0, :2], "o", color="tab:green", label="start")
    ax.plot(*ref[-1, :2], "s", color="tab:red", label="end")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(f"{title}: centre of mass from above")
    fig.tight_layout()
    fig.savefig(file, dpi=120)
    plt.close(fig)


def plot_errors(
    t: NDArray[np.float64],
    series: dict[str, NDArray[np.float64]],
    file: Path,
    title: str,
    marks: NDArray[np.float64] | None = None,
) -> None:
    """Error curves (m) over time (s), in centimetres; ``marks`` are times to flag
    (re-initialisations)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for label, values in series.items():
        ax.plot(t, 100.0 * values, label=label)
    if marks is not None:
        for k, x in enumerate(marks):
            ax.axvline(x, color="tab:red", alpha=0.4, label="re-initialised" if k == 0 else None)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("error (cm)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(file, dpi=120)
    plt.close(fig)
