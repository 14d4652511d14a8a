"""Search a face-to-face rolling gait for a robot preset (a developer tool).

    python scripts/find_gait.py three_bar_large [--max-combo 3] [--hold 25] [--settle 10]

From the resting face, every candidate action (one, two or three actuated cables fully
contracted, the others held or fully let out) is tried for ``--hold`` control steps and
followed by ``--settle`` steps with the initial rest lengths, on the simulator's ground
truth. The transition to a new support face that moves the centre of mass furthest in
the direction of travel so far is kept, and the search goes on from the face reached,
until it returns to a face it has seen. It prints the ``gait:`` section to paste into
the preset's YAML (``tensegrity_gym/model/assets/<robot>.yaml``), which
:class:`tensegrity_gym.tasks.gaits.FaceGait` reads; the log goes to stderr.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import tensegrity_gym  # noqa: F401  (registers the envs)


def candidates(m: int, max_combo: int, hold: np.ndarray) -> list[tuple[tuple[int, ...], str, Any]]:
    """Every (contracted actuated indices, "hold" | "out", action (m,)) to try."""
    out = []
    for r in range(1, max_combo + 1):
        for combo in itertools.combinations(range(m), r):
            for rest in ("hold", "out"):
                a = hold.copy() if rest == "hold" else np.ones(m, dtype=np.float32)
                a[list(combo)] = -1.0
                out.append((combo, rest, a))
    return out


def search(robot: str, max_combo: int, hold_steps: int, settle_steps: int) -> dict[str, Any]:
    """The gait section (names, as the YAML holds it) found for ``robot``."""
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", robot=robot, estimator="oracle").unwrapped
    env.reset(seed=0)
    d = env.backend.description
    world = env.backend.world
    hold = env.targets_to_action(d.rest_lengths[d.actuated])

    def face() -> tuple[int, ...]:
        z = env.backend.ground_truth().node_positions[:, 2]
        return tuple(sorted(np.argsort(z, kind="stable")[:3].tolist()))

    def run(a: np.ndarray) -> None:
        for _ in range(hold_steps):
            env.step(a)
        for _ in range(settle_steps):
            env.step(hold)

    tried = candidates(d.n_actuated, max_combo, hold)
    run(hold)
    faces: list[dict[str, Any]] = []
    seen = [face()]
    heading = None
    while True:
        start = world.save_state()
        c0 = env.backend.ground_truth().com[:2].copy()
        best = None
        for combo, rest, a in tried:
            world.restore_state(start)
            run(a)
            f = face()
            if f == seen[-1] or (f in seen[:-1] and f != seen[0]):
                continue
            dc = env.backend.ground_truth().com[:2] - c0
            score = float(dc @ heading) if heading is not None else float(np.linalg.norm(dc))
            if best is None or score > best[0]:
                best = (score, combo, rest, a, f, dc)
        if best is None or best[0] <= 0.0:
            print("# stuck at", seen[-1], file=sys.stderr)
            break
        _, combo, rest, a, f, dc = best
        print(f"# {seen[-1]} {combo} {rest} -> {f}, CoM {dc.round(3).tolist()}", file=sys.stderr)
        faces.append(
            {
                "face": [d.nodes[i].name for i in seen[-1]],
                "contract": [d.cables[int(d.actuated[k])].name for k in combo],
                "others": rest,
            }
        )
        heading = dc / np.linalg.norm(dc) if heading is None else heading
        world.restore_state(start)
        run(a)
        if f in seen:
            break
        seen.append(f)
    env.close()
    return {"hold_steps": hold_steps, "settle_steps": settle_steps, "faces": faces}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("robot")
    parser.add_argument("--max-combo", type=int, default=3)
    parser.add_argument("--hold", type=int, default=25, help="control steps of a contraction")
    parser.add_argument("--settle", type=int, default=10, help="control steps of the rest")
    args = parser.parse_args()
    gait = search(args.robot, args.max_combo, args.hold, args.settle)
    print(yaml.safe_dump({"gait": gait}, sort_keys=False, default_flow_style=None, width=100))


if __name__ == "__main__":
    main()
