"""Search a face-to-face rolling gait for a robot preset (a developer tool).

    python scripts/find_gait.py three_bar

From the resting face, every candidate action (one, two or three actuated cables fully
contracted, the others held or fully let out) is tried for ``HOLD`` control steps and
followed by ``SETTLE`` steps with the initial rest lengths. The transition to a new
support face that moves the centre of mass furthest in the direction of travel so
far is kept, and the search goes on from the face reached, until it returns to a face
it has seen. It prints the face -> action table that ``tensegrity_gym.tasks.gaits``
holds for the preset.
"""

from __future__ import annotations

import itertools
import sys

import gymnasium as gym
import numpy as np

import tensegrity_gym  # noqa: F401  (registers the envs)

HOLD, SETTLE = 25, 10


def main(robot: str, max_combo: int) -> None:
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", robot=robot).unwrapped
    env.reset(seed=0)
    d = env.backend.description
    world = env.backend.world
    m = d.n_actuated
    hold = env.targets_to_action(d.rest_lengths[d.actuated])

    def face() -> tuple[int, ...]:
        z = env.backend.ground_truth().node_positions[:, 2]
        return tuple(sorted(np.argsort(z)[:3].tolist()))

    save, restore = world.save_state, world.restore_state

    def run(a: np.ndarray) -> None:
        for _ in range(HOLD):
            env.step(a)
        for _ in range(SETTLE):
            env.step(hold)

    candidates = []
    for r in range(1, max_combo + 1):
        for combo in itertools.combinations(range(m), r):
            for rest in ("hold", "out"):
                a = hold.copy() if rest == "hold" else np.ones(m, dtype=np.float32)
                a[list(combo)] = -1.0
                candidates.append((combo, rest, a))
    run(hold)
    table = []
    seen = [face()]
    heading = None
    while True:
        start = save()
        c0 = env.backend.ground_truth().com[:2].copy()
        best = None
        for combo, rest, a in candidates:
            restore(start)
            run(a)
            f = face()
            dc = env.backend.ground_truth().com[:2] - c0
            if f == seen[-1] or (f in seen[:-1] and f != seen[0]):
                continue
            score = float(dc @ heading) if heading is not None else float(np.linalg.norm(dc))
            if best is None or score > best[0]:
                best = (score, combo, rest, f, dc)
        if best is None or best[0] <= 0.0:
            print("# stuck at", seen[-1], file=sys.stderr)
            break
        score, combo, rest, f, dc = best
        print(f"    ({seen[-1]}, {combo}, {rest!r}),  # -> {f}, CoM {dc.round(3).tolist()}")
        table.append((seen[-1], combo, rest))
        heading = dc / np.linalg.norm(dc) if heading is None else heading
        restore(start)
        run(candidates[[c[:2] for c in candidates].index((combo, rest))][2])
        if f in seen:
            break
        seen.append(f)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 3)
