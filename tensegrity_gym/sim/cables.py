"""The cable and motor arithmetic of one physics step, compiled.

Kept apart from :mod:`tensegrity_gym.sim.world` (which alone talks to PyBullet) so that
the per-step loop crosses into Python only for PyBullet's own calls.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba
import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = ["cable_wrenches", "slew_motors"]


@numba.njit(cache=True, nogil=True)
def slew_motors(
    rest: NDArray[np.float64],
    actuated: NDArray[np.int64],
    targets: NDArray[np.float64],
    max_step: NDArray[np.float64],
) -> bool:
    """Move the actuated rest lengths (m) toward ``targets`` by at most ``max_step``,
    in place. Returns whether any motor is still moving."""
    moving = False
    for i in range(actuated.shape[0]):
        k = actuated[i]
        err = targets[i] - rest[k]
        if err > max_step[i]:
            rest[k] += max_step[i]
            moving = True
        elif err < -max_step[i]:
            rest[k] -= max_step[i]
            moving = True
        else:
            rest[k] = targets[i]
    return moving


@numba.njit(cache=True, nogil=True)
def cable_wrenches(
    poses: NDArray[np.float64],
    half: NDArray[np.float64],
    node_of: NDArray[np.int64],
    cables: NDArray[np.int64],
    stiffness: NDArray[np.float64],
    damping: NDArray[np.float64],
    rest: NDArray[np.float64],
    reel: NDArray[np.float64],
    spool: NDArray[np.float64],
    prev_len: NDArray[np.float64],
    inv_dt: float,
    n_nodes: int,
    wrench: NDArray[np.float64],
) -> None:
    """Force and torque (about the rod centre) that the cables put on each rod.

    Args:
        poses: (r, 7) rod centre (3) and quaternion (x, y, z, w); node a of a rod sits at
            centre - half * body z, node b at centre + half * body z.
        cables: (k, 2) node pairs; tension K (L - L0) + c dL/dt when stretched, never
            negative, with dL/dt by a backward difference against ``prev_len`` (updated
            in place: one step of lag, far below the damping time constants).
        rest: (k,) rest lengths (m) the motors' positions (and the passive cables) set.
        reel: (k,) least stretch (m) of a cable whose motor holds a minimum tension (that
            tension over the stiffness), NaN for the others: its spool pays out no
            further than ``rest`` and reels in any slack, so its rest length is
            min(rest, L - reel), below the motor's command range where the endcaps come
            closer (the spool winds the cable on), and while it is short of ``rest``
            the tension is the minimum's, with no damping (the spool turns freely).
        spool: (k,) output, the rest lengths in effect (m): the encoders' readings.
        wrench: (r, 6) output, force then torque (N, N m), overwritten.
    """
    n_rods = poses.shape[0]
    x = np.zeros((n_nodes, 3))
    for r in range(n_rods):
        qx, qy, qz, qw = poses[r, 3], poses[r, 4], poses[r, 5], poses[r, 6]
        h = half[r]
        ax = 2.0 * (qx * qz + qw * qy) * h
        ay = 2.0 * (qy * qz - qw * qx) * h
        az = (1.0 - 2.0 * (qx * qx + qy * qy)) * h
        a, b = node_of[r, 0], node_of[r, 1]
        x[a, 0], x[a, 1], x[a, 2] = poses[r, 0] - ax, poses[r, 1] - ay, poses[r, 2] - az
        x[b, 0], x[b, 1], x[b, 2] = poses[r, 0] + ax, poses[r, 1] + ay, poses[r, 2] + az
    f = np.zeros((n_nodes, 3))
    for k in range(cables.shape[0]):
        i, j = cables[k, 0], cables[k, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        rate = (length - prev_len[k]) * inv_dt
        prev_len[k] = length
        least = reel[k]
        if least == least and rest[k] > length - least:  # not NaN, and short of slack:
            # the spool turns under the motor's minimum torque, reeling in or paying
            # out as the endcaps move; the cable holds that tension, undamped.
            spool[k] = length - least
            tension = stiffness[k] * least
        else:
            spool[k] = rest[k]
            stretch = length - rest[k]
            if stretch <= 0.0:
                continue  # slack: cables only pull
            tension = stiffness[k] * stretch + damping[k] * rate
        if tension <= 0.0:
            continue
        q = tension / length
        f[i, 0] += q * dx
        f[i, 1] += q * dy
        f[i, 2] += q * dz
        f[j, 0] -= q * dx
        f[j, 1] -= q * dy
        f[j, 2] -= q * dz
    for r in range(n_rods):
        a, b = node_of[r, 0], node_of[r, 1]
        # Torque about the centre: r_a x f_a + r_b x f_b, with r_a = -r_b.
        rx = x[b, 0] - poses[r, 0]
        ry = x[b, 1] - poses[r, 1]
        rz = x[b, 2] - poses[r, 2]
        gx, gy, gz = f[b, 0] - f[a, 0], f[b, 1] - f[a, 1], f[b, 2] - f[a, 2]
        wrench[r, 0] = f[a, 0] + f[b, 0]
        wrench[r, 1] = f[a, 1] + f[b, 1]
        wrench[r, 2] = f[a, 2] + f[b, 2]
        wrench[r, 3] = ry * gz - rz * gy
        wrench[r, 4] = rz * gx - rx * gz
        wrench[r, 5] = rx * gy - ry * gx
