"""The ground under the simulated robot: a height map, and builders of one by name.

A :class:`Terrain` is a regular grid of heights (m); the simulator
(:class:`~tensegrity_gym.sim.world.PhysicsWorld`) builds it as a PyBullet heightfield,
or as today's infinite plane when it is flat. ``gym.make(ID, terrain=...)`` takes:

- ``"flat"`` (the default): the plane at z = 0, exactly as without the argument;
- ``"valley"``: a smooth ring-shaped trough around the start (:func:`valley`), the same
  every episode, that the robot rolls down into and up out of whatever its heading;
- ``"rough"``: random smooth bumps (:func:`rough`) drawn at each reset from the reset's
  rng, so a seed fixes the ground bit for bit;
- a path to a ``.npy`` or ``.png`` height map with a YAML sidecar (:func:`load_terrain`);
- a :class:`Terrain` object, or a lab's own name registered in :data:`TERRAINS`::

      register_terrain("stairs", lambda description, rng: Terrain(...))

The map ends at its edges: the simulator has no ground beyond them.

No estimator is told the map: the UKF's ground model assumes flat ground at z = 0, as
a real robot's would without a survey of the site.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from tensegrity_gym.model.checks import yaml_problem
from tensegrity_gym.model.registry import Registry

if TYPE_CHECKING:
    from collections.abc import Callable

    from numpy.typing import ArrayLike, NDArray

    from tensegrity_gym.model.description import RobotDescription

    TerrainBuilder = Callable[[RobotDescription, np.random.Generator], "Terrain"]

__all__ = [
    "MAX_SLOPE",
    "TERRAINS",
    "FixedTerrain",
    "Terrain",
    "flat",
    "load_terrain",
    "register_terrain",
    "rough",
    "terrain_builder",
    "valley",
]

# Built maps span +-_HALF_SPAN rod lengths around the origin (Tong et al. 2024's robot rolled
# 15 L through its valley), _CELL rod lengths a cell: Bullet's cost of a rod's contact
# with a heightfield grows with the triangles under it (a tenth of L: 10x the plane's
# step time; a quarter: about 2x).
_HALF_SPAN = 16.0
_CELL = 0.25

MAX_SLOPE = 100.0
"""The steepest rise (m/m) between neighbouring heights a map may have (89.4 degrees):
a wall 1 m high on 1 cm cells. Beyond it a map is almost surely mis-scaled
(``height_scale`` or ``cell_size`` off by orders of magnitude), and its near-vertical
triangles throw a resting robot into the air."""


@dataclass(frozen=True, eq=False)
class Terrain:
    """A height map: ``heights[r, c]`` (m) is the ground at x = ``origin[0] + c *
    cell_size``, y = ``origin[1] + r * cell_size``; bilinear in between.

    Args:
        heights: (rows, cols), rows and cols >= 2, finite (m); kept as a read-only copy.
        cell_size: grid spacing (m), > 0.
        origin: world (x, y) of ``heights[0, 0]`` (m).
        name: for messages.
    """

    heights: NDArray[np.float64]
    cell_size: float
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = ""

    def __post_init__(self) -> None:
        h = np.array(self.heights, dtype=np.float64)
        cell = float(self.cell_size)
        wrong = _grid_error(h, cell, self.origin)
        if wrong is not None:
            raise ValueError(
                f"Terrain {self.name!r}: {wrong}" if self.name else f"Terrain: {wrong}"
            )
        h.setflags(write=False)
        object.__setattr__(self, "heights", h)
        object.__setattr__(self, "cell_size", cell)
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))

    @property
    def is_flat(self) -> bool:
        """Zero everywhere: the simulator keeps its infinite plane at z = 0."""
        return not np.any(self.heights)

    @property
    def steepest_slope(self) -> float:
        """The largest |height difference| / cell_size (m/m) between neighbouring heights."""
        return _steepest_slope(self.heights, self.cell_size)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the map (m)."""
        rows, cols = self.heights.shape
        x0, y0 = self.origin
        return x0, x0 + (cols - 1) * self.cell_size, y0, y0 + (rows - 1) * self.cell_size

    def height_at(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """Ground height (m) at world (x, y) (m, any broadcastable shapes), bilinear;
        beyond the edges, the nearest edge's height."""
        h = self.heights
        rows, cols = h.shape
        u = np.clip(
            (np.asarray(x, dtype=np.float64) - self.origin[0]) / self.cell_size, 0.0, cols - 1
        )
        v = np.clip(
            (np.asarray(y, dtype=np.float64) - self.origin[1]) / self.cell_size, 0.0, rows - 1
        )
        c = np.minimum(np.floor(u).astype(np.intp), cols - 2)
        r = np.minimum(np.floor(v).astype(np.intp), rows - 2)
        fu, fv = u - c, v - r
        low = h[r, c] * (1.0 - fu) + h[r, c + 1] * fu
        high = h[r + 1, c] * (1.0 - fu) + h[r + 1, c + 1] * fu
        return np.asarray(low * (1.0 - fv) + high * fv)

    def slope_at(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """|grad h| (m/m) at world (x, y) (m), by central differences half a cell wide."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        d = 0.5 * self.cell_size
        gx = (self.height_at(x + d, y) - self.height_at(x - d, y)) / (2.0 * d)
        gy = (self.height_at(x, y + d) - self.height_at(x, y - d)) / (2.0 * d)
        return np.asarray(np.hypot(gx, gy))

    def clearance(self, points: ArrayLike, radius: ArrayLike) -> NDArray[np.float64]:
        """Gap (m) between spheres of ``radius`` (m, (k,) or scalar) at ``points`` (k, 3)
        (m) and the ground, along its normal (locally planar): < 0 where they sink in."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        h = self.height_at(p[:, 0], p[:, 1])
        g = self.slope_at(p[:, 0], p[:, 1])
        return np.asarray((p[:, 2] - h) / np.sqrt(1.0 + g * g) - np.asarray(radius))

    def lift(self, points: ArrayLike, radius: ArrayLike) -> float:
        """The least upward shift (m) that puts spheres of ``radius`` (m) at ``points``
        (k, 3) (m), resting on or above the plane z = 0, on or above this ground."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), p.shape[:1])
        h = self.height_at(p[:, 0], p[:, 1])
        g = self.slope_at(p[:, 0], p[:, 1])
        return float(np.max(h + r * np.sqrt(1.0 + g * g) - np.maximum(p[:, 2], r)))


def _steepest_slope(heights: NDArray[np.float64], cell_size: float) -> float:
    """The largest |difference| (m) between neighbouring ``heights`` over ``cell_size`` (m)."""
    rise = max(float(np.abs(np.diff(heights, axis=a)).max()) for a in (0, 1))
    return rise / cell_size


def _grid_error(heights: NDArray[np.float64], cell_size: float, origin: object) -> str | None:
    """What is wrong with a grid of ``heights`` (m) ``cell_size`` (m) apart whose first
    cell is at ``origin`` (x, y) (m), or None."""
    if heights.ndim != 2 or min(heights.shape) < 2:
        return f"heights must be (rows, cols) with both >= 2, got shape {heights.shape}"
    if not np.all(np.isfinite(heights)):
        return "heights must all be finite"
    if not (math.isfinite(cell_size) and cell_size > 0.0):
        return f"cell_size={cell_size!r} must be finite and > 0"
    try:
        xy = np.asarray(origin, dtype=np.float64)
    except (TypeError, ValueError):
        xy = np.full(1, np.nan)
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        return f"origin={origin!r} must be two finite numbers [x, y] (m)"
    slope = _steepest_slope(heights, cell_size)
    if slope > MAX_SLOPE:
        return (
            f"neighbouring heights rise {slope:.3g} m per m (cell_size {cell_size:g} m), "
            f"steeper than {MAX_SLOPE:g} (89.4 degrees): check height_scale and cell_size"
        )
    return None


# ------------------------------------------------------------------ builders


def _grid(description: RobotDescription) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """World x (1, n) and y (n, 1) of a square map +-_HALF_SPAN rod lengths wide (m), and
    its cell size (m)."""
    length = description.characteristic_length
    n = round(2.0 * _HALF_SPAN / _CELL) + 1
    axis = (np.arange(n, dtype=np.float64) - 0.5 * (n - 1)) * (_CELL * length)
    return axis[None, :], axis[:, None], _CELL * length


def flat(description: RobotDescription, rng: np.random.Generator) -> Terrain:
    """The plane z = 0 (the default): draws nothing from ``rng``."""
    del description, rng
    return Terrain(np.zeros((2, 2)), 1.0, (-0.5, -0.5), name="flat")


def valley(
    description: RobotDescription,
    rng: np.random.Generator,
    *,
    inner: float = 1.0,
    width: float = 5.0,
    depth: float = 0.25,
) -> Terrain:
    """A ring-shaped cosine trough around the origin, in rod lengths L: flat out to
    ``inner`` L, down ``depth`` L over ``width`` / 2 and up again (steepest slope pi *
    depth / width: 9 degrees by default), flat beyond. Deterministic (``rng`` unused).

    At Tong et al. 2024's scale (a 1.45 m robot) the trough is 7.3 m across and 0.36 m deep.
    """
    del rng
    x, y, cell = _grid(description)
    length = description.characteristic_length
    half = 0.5 * width * length
    u = (np.hypot(x, y) - (inner * length + half)) / half
    h = np.where(np.abs(u) < 1.0, -0.5 * depth * length * (1.0 + np.cos(np.pi * u)), 0.0)
    return Terrain(h, cell, (float(x[0, 0]), float(y[0, 0])), name="valley")


def rough(
    description: RobotDescription,
    rng: np.random.Generator,
    *,
    amplitude: float = 0.02,
    correlation: float = 0.5,
) -> Terrain:
    """Smooth random bumps: white noise from ``rng`` low-passed by a Gaussian of
    ``correlation`` rod lengths (std), scaled to an RMS height of ``amplitude`` rod
    lengths around a mean of 0 (6.5 mm RMS on the 3-bar robot). The map is periodic.
    """
    x, y, cell = _grid(description)
    length = description.characteristic_length
    noise = rng.standard_normal((y.shape[0], x.shape[1]))
    sigma = correlation * length / cell  # cells
    fy = np.fft.fftfreq(noise.shape[0])[:, None]
    fx = np.fft.rfftfreq(noise.shape[1])[None, :]
    gain = np.exp(-2.0 * (np.pi * sigma) ** 2 * (fx * fx + fy * fy))
    h = np.fft.irfft2(np.fft.rfft2(noise) * gain, s=noise.shape)
    h -= h.mean()
    h *= amplitude * length / h.std()
    return Terrain(h, cell, (float(x[0, 0]), float(y[0, 0])), name="rough")


# ------------------------------------------------------------------ files


def _read_sidecar(path: Path) -> dict[str, Any]:
    """The ``<stem>.yaml`` next to a height map, as a mapping."""
    sidecar = path.with_suffix(".yaml")
    if not sidecar.is_file():
        raise ValueError(f"its sidecar {sidecar.name} (cell_size, height_scale, origin) is missing")
    try:
        doc = yaml.safe_load(sidecar.read_text(encoding="utf-8"))
    except OSError as err:
        raise ValueError(f"{sidecar.name} could not be read: {err.strerror or err}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{sidecar.name} is not YAML text (not UTF-8)") from None
    except yaml.YAMLError as err:
        raise ValueError(f"{sidecar.name} is not valid YAML: {yaml_problem(err)}") from None
    if not isinstance(doc, dict) or "cell_size" not in doc:
        raise ValueError(f"{sidecar.name} must be a mapping with cell_size (m)")
    unknown = sorted(set(doc) - {"cell_size", "height_scale", "origin"})
    if unknown:
        raise ValueError(
            f"{sidecar.name}: unknown keys {unknown}; valid: cell_size, height_scale, origin"
        )
    return doc


def _read_heights(path: Path) -> NDArray[np.float64]:
    """The raw grid of a ``.npy`` (as stored) or greyscale ``.png`` (0 black to 1 white,
    flipped so that the image's top row is the map's largest y)."""
    if path.suffix.lower() == ".npy":
        return np.asarray(np.load(path, allow_pickle=False), dtype=np.float64)
    from matplotlib.image import imread

    try:
        image = np.asarray(imread(path), dtype=np.float64)
    except SyntaxError as err:  # Pillow's word for a file that is no PNG
        raise ValueError(f"not a PNG image ({err.msg})") from None
    if image.ndim == 3:
        if not np.all(image[..., :3] == image[..., :1]):
            raise ValueError("the image is not greyscale")
        image = image[..., 0]
    return np.ascontiguousarray(image[::-1])


def load_terrain(path: str | os.PathLike[str]) -> Terrain:
    """A height map from a file, or ValueError naming it.

    ``PATH.npy`` holds heights (rows, cols) (``heights[r, c]`` at x = origin x + c *
    cell_size, y = origin y + r * cell_size); ``PATH.png`` is a greyscale image seen from
    above (+x right, +y up), black 0. The sidecar ``PATH`` with ``.yaml`` for its suffix
    gives ``cell_size`` (m, required), ``height_scale`` (m per unit: a .npy's values, or
    white in a .png; default 1) and ``origin`` ([x, y] (m) of the first cell; default:
    the map centred on the world origin).
    """
    p = Path(path)
    try:
        if p.suffix.lower() not in (".npy", ".png"):
            raise ValueError("expected a .npy or .png height map")
        if not p.is_file():
            raise ValueError("no such file")
        raw = _read_heights(p)
        doc = _read_sidecar(p)
        raw = raw * float(doc.get("height_scale", 1.0))
        rows, cols = raw.shape if raw.ndim == 2 else (0, 0)
        cell = float(doc["cell_size"])
        default = (-0.5 * (cols - 1) * cell, -0.5 * (rows - 1) * cell)
        origin = doc.get("origin", default)
        wrong = _grid_error(raw, cell, origin)
        if wrong is not None:
            raise ValueError(wrong)
        ox, oy = (float(v) for v in origin)
    except (ValueError, TypeError, OSError) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ValueError(f"terrain={os.fspath(path)!r}: {reason}") from None
    return Terrain(raw, cell, (ox, oy), name=p.name)


# ------------------------------------------------------------------ registry


def _builder_from_plugin(name: str, obj: Any) -> TerrainBuilder:
    del name
    if callable(obj):
        return obj  # type: ignore[no-any-return]
    raise TypeError(
        f"expected a terrain builder (description, rng) -> Terrain, got {type(obj).__name__}"
    )


TERRAINS: Registry[TerrainBuilder] = Registry(
    "terrain", "tensegrity_gym.terrains", _builder_from_plugin
)
"""Terrain name -> builder ``(description, rng) -> Terrain``, called at each reset with
the reset's rng (entry-point group ``tensegrity_gym.terrains`` for installed packages)."""


def register_terrain(name: str, builder: TerrainBuilder, *, overwrite: bool = False) -> None:
    """Register a terrain: ``gym.make(ID, terrain=name)`` then builds it at each reset."""
    TERRAINS.register(name, builder, overwrite=overwrite)


register_terrain("flat", flat)
register_terrain("valley", valley)
register_terrain("rough", rough)


@dataclass(frozen=True)
class FixedTerrain:
    """The builder of one map, the same every episode (a file or a :class:`Terrain`):
    the simulator can check it at ``make``, before any episode."""

    terrain: Terrain

    def __call__(self, description: RobotDescription, rng: np.random.Generator) -> Terrain:
        del description, rng
        return self.terrain


def terrain_builder(terrain: object) -> TerrainBuilder:
    """The builder a ``terrain`` argument means: a name in :data:`TERRAINS`, a height
    map file (read now), or a :class:`Terrain`; else ValueError ``"terrain=...: ..."``."""
    if isinstance(terrain, Terrain):
        return FixedTerrain(terrain)
    if isinstance(terrain, str) and terrain in TERRAINS:
        return TERRAINS[terrain]
    if isinstance(terrain, (str, os.PathLike)):
        if Path(terrain).suffix.lower() in (".npy", ".png"):
            return FixedTerrain(load_terrain(terrain))
        raise ValueError(
            f"terrain={terrain!r}: not a registered terrain "
            f"({list(TERRAINS.names())}) nor a .npy or .png height map"
        )
    raise ValueError(f"terrain={terrain!r} must be a terrain name, a height map path or a Terrain")
