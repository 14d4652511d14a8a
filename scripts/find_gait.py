"""Search a face-to-face rolling gait for a robot preset (a developer tool).

    python scripts/find_gait.py three_bar_large [--direction forward|backward]
        [--turn left|right [--candidates 6]] [--steer [--per-pair 2] [--starts 3] [--share 0.6]]
        [--seeds 0 1 2 3] [--max-combo 3]
        [--hold 25] [--settle 10] [--ramp 0] [--steps 600] [--restarts 4] [--cache FILE]

The robot starts as an episode does (``reset(seed)``, on the simulator's ground truth)
and is run in closed loop, one gait period at a time, exactly as
:class:`tensegrity_gym.tasks.gaits.FaceGait` runs a table: on a support face the table
has, its action; on a face met for the first time, every candidate action (one, two or
three actuated cables fully contracted, the others held at their initial rest length or
let out to their maximum) is tried for ``--hold`` control steps and ``--settle`` steps
of the initial rest lengths (the commands moved along ramps of ``--ramp`` steps across
the motors' range, as the gait's ``ramp_steps``), and the best is entered in the table.
A transition depends on the state it starts from (the cables are not all back at their
rest lengths after ``--settle``, and the reset's random yaw changes how a flip lands), so
the table is run from every reset of ``--seeds`` in turn: a face met later gets its own
entry, and an entry that leaves the robot on its face (a stall) is struck from that
face's choices and the search starts again (``--restarts``). The objectives:

- ``--direction forward``: the CoM furthest along the first transition's heading
  (fixed to the robot's body: the start's support triangle), to a new face or the
  table's first.
- ``--direction backward``: the same, opposite to where the robot's own ``gait``
  (forward) carries it from the first seed over one pass of its table: tipping over
  the far edges of the support triangles.
- ``--turn left|right``: from a resting state on every face the robot reaches, every
  candidate (a model of the transitions: new face, CoM move and yaw change in the
  face's frame); the ``--candidates`` cycles of 2 to 4 faces that the model says turn
  most that way while moving are each completed with the way into them from every
  seed, run, and the one whose worst seed turns most (degrees a period, from the
  support triangle's yaw on its most visited face, times the CoM's metres a period)
  is kept. A rolling prism's path zig-zags; a cycle with a net rotation turns.
- ``--steer``: a steering gait, no table: the same model, from the first seed's reset.
  Each distinct outcome is run again from up to ``--starts`` resting states on its face
  (the robot arrived from its other neighbours) and kept where it leads to the same
  face from at least ``--share`` of them, with its mean move (a marginal tumble, which
  a policy's corrections or a real robot's motors tip the other way, is dropped). Each
  face keeps up to ``--per-pair`` of those (the most common first) for every face it
  leads to, those that move the CoM at least half of MIN_MOVE, each with its move in
  the face's frame and the face it leads to (FaceGait chooses among them by the goal).
  Printed as ``gaits: {steer: ...}``; nothing is run in closed loop.

Where a sequence of actions from a reset leaves the robot is cached, in memory and in
``--cache`` (JSON, reused by a later run with the same robot and timing, so that the
objectives share their transitions). The table found is run as FaceGait runs it for
``--steps`` control steps from every seed and measured (CoM path from rest to rest:
metres and degrees a period, steps to 5 m). It prints the section to paste into the
preset's YAML (``tensegrity_gym/model/assets/<robot>.yaml``), ``gait:`` for forward,
``gaits: {NAME: ...}`` for the others, under a comment saying what it does; the log
goes to stderr.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import tensegrity_gym  # noqa: F401  (registers the envs)
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.tasks.gaits import (
    FaceGait,
    face_yaw,
    gait_table,
    lowest_face,
    period_commands,
)
from tensegrity_gym.tasks.gaits import turned as rotated

Face = tuple[int, ...]
Route = tuple[int, ...]  # candidate indices run one period each from the reset
Table = dict[Face, int]  # face -> candidate index
Model = dict[tuple[Face, int], tuple[Face, np.ndarray]]  # see explore
TRAVEL = 5.0  # m of CoM path the evaluation's runs need (Tong et al. 2024, table II)
MIN_MOVE = 0.1  # m a gait period the model's turning cycles carry the CoM at least
CACHE_VERSION = 3


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


def unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


class Rollouts:
    """The robot from ``reset(seed)``, a gait period at a time: where each path leaves
    it (support face, CoM x and y in m, the support triangle's yaw in rad), cached in
    :attr:`cache` ("i,j,k" -> [face nodes..., x, y, yaw])."""

    def __init__(self, args: argparse.Namespace, seed: int, cache: dict[str, list[float]]) -> None:
        env = gym.make("tensegrity_gym/ThreeBarRoll-v0", robot=args.robot, estimator="oracle")
        self.env = env.unwrapped
        self.env.reset(seed=seed)
        d = self.env.backend.description
        self.description, self.seed = d, seed
        self.world = self.env.backend.world
        self.hold = self.env.targets_to_action(d.rest_lengths[d.actuated])
        self.tried = candidates(d.n_actuated, args.max_combo, self.hold)
        self.hold_steps, self.settle_steps, self.ramp_steps = args.hold, args.settle, args.ramp
        self.cache = cache
        # A path's state: the world's and the command the ramp has reached.
        self._commanded = self.hold.copy()
        self._states = {(): (self.world.save_state(), self._commanded)}
        self._record(())
        self.yaw0 = self.outcome(())[2]

    def _record(self, path: Route) -> None:
        truth = self.env.backend.ground_truth()
        face = lowest_face(truth.node_positions)
        yaw = face_yaw(truth.node_positions, face)
        self.cache[",".join(map(str, path))] = [*face, *truth.com[:2].tolist(), yaw]

    def outcome(self, path: Route) -> tuple[Face, np.ndarray, float]:
        """The support face, CoM (x, y, m) and its yaw (rad) at the end of ``path``."""
        key = ",".join(map(str, path))
        if key not in self.cache:
            self._run(path)
        v = self.cache[key]
        return tuple(int(i) for i in v[:3]), np.array(v[3:5]), float(v[5])

    def _run(self, path: Route) -> None:
        """Simulate ``path`` from its longest saved prefix, saving the state before its
        last action (from where the search tries the others)."""
        n = max(i for i in range(len(path)) if path[:i] in self._states)
        world, self._commanded = self._states[path[:n]]
        self.world.restore_state(world)
        for i in range(n, len(path)):
            if i == len(path) - 1 and path[:i] not in self._states:
                self._states[path[:i]] = (self.world.save_state(), self._commanded)
            steps = (self.hold_steps, self.settle_steps, self.ramp_steps)
            for command in period_commands(
                self._commanded, self.tried[path[i]][2], self.hold, steps
            ):
                self.env.step(command)
                self._commanded = command
            self._record(path[: i + 1])

    def close(self) -> None:
        self.env.close()


class Heading:
    """Score a transition by how far it carries the CoM (m) along a heading fixed to the
    robot's body (the start's support triangle); None: the first transition's."""

    def __init__(self, body: np.ndarray | None) -> None:
        self.body = body

    def __call__(self, sim: Rollouts, table: Table, to: Face, moved: np.ndarray) -> float:
        if self.body is None:
            return float(np.linalg.norm(moved))
        return float(moved @ rotated(self.body, sim.yaw0))

    def chose(self, sim: Rollouts, moved: np.ndarray) -> None:
        if self.body is None:
            self.body = rotated(unit(moved), -sim.yaw0)


class IntoTable(Heading):
    """Score 1 a transition onto a face of the table, 0 another: the way into a cycle."""

    def __init__(self) -> None:
        super().__init__(np.zeros(2))

    def __call__(self, sim: Rollouts, table: Table, to: Face, moved: np.ndarray) -> float:
        return 1.0 if to in table else 0.0


def best_action(
    sim: Rollouts, path: Route, table: Table, banned: set[tuple[Face, int]], score: Heading
) -> int | None:
    """The candidate ``score`` rates best from the end of ``path``, among those that
    move the robot to a new face or the table's first; failing those, to another face
    of the table (None: none scores above 0)."""
    face, com, _ = sim.outcome(path)
    first = next(iter(table), None)
    best: dict[bool, tuple[float, int]] = {}
    for k in range(len(sim.tried)):
        to, c, _ = sim.outcome((*path, k))
        s = score(sim, table, to, c - com)
        closes = to not in table or to == first
        if to != face and (face, k) not in banned and s > best.get(closes, (0.0, -1))[0]:
            best[closes] = (s, k)
    choice = best.get(True, best.get(False))
    return None if choice is None else choice[1]


def grow(
    sim: Rollouts, table: Table, score: Heading, periods: int, banned: set[tuple[Face, int]]
) -> tuple[Face, int] | None:
    """Run ``table`` in closed loop for ``periods``, entering the best action for each
    face met first; the entry that stalled (left the robot on its face), if one did."""
    path: Route = ()
    for i in range(periods):
        face, com, _ = sim.outcome(path)
        if face not in table:
            k = best_action(sim, path, table, banned, score)
            if k is None:
                print(f"# seed {sim.seed}: stuck on {face} after {i} periods", file=sys.stderr)
                return None
            table[face] = k
            to, moved, _ = sim.outcome((*path, k))
            moved -= com
            score.chose(sim, moved)
            print(
                f"# seed {sim.seed}: {face} {sim.tried[k][:2]} -> {to}, CoM {moved.round(3)}",
                file=sys.stderr,
            )
        if sim.outcome((*path, table[face]))[0] == face:
            return face, table[face]
        path = (*path, table[face])
    return None


def search(
    sims: list[Rollouts], start: Table, score: Heading, periods: int, restarts: int
) -> Table:
    """:func:`grow` ``start`` on each seed in turn; an entry that stalls is struck and the
    search starts again, up to ``restarts`` times."""
    banned: set[tuple[Face, int]] = set()
    while True:
        table = {f: k for f, k in start.items() if (f, k) not in banned}
        stalled = None
        for sim in sims:
            stalled = grow(sim, table, score, periods, banned)
            if stalled is not None:
                break
        if stalled is None or len(banned) >= restarts:
            return table
        print(f"# stalled on {stalled[0]} with {sims[0].tried[stalled[1]][:2]}", file=sys.stderr)
        banned.add(stalled)


def transition(sim: Rollouts, path: Route, k: int) -> tuple[Face, np.ndarray]:
    """Where candidate ``k`` run after ``path`` leaves the robot: (new face, the move in
    the frame of the face ``path`` ends on: CoM x, y in m along and across its
    triangle's yaw, the yaw's change in rad)."""
    _, com, yaw = sim.outcome(path)
    to, c, y = sim.outcome((*path, k))
    turn = (y - yaw + np.pi) % (2.0 * np.pi) - np.pi
    return to, np.array([*rotated(c - com, -yaw), turn])


def explore(sim: Rollouts) -> tuple[Model, dict[Face, Route]]:
    """Every candidate from a resting state on every face the robot reaches from the
    reset (the first state found on it): the model, (face, candidate) ->
    :func:`transition`, and the path that first reached each face."""
    paths: dict[Face, Route] = {sim.outcome(())[0]: ()}
    model: Model = {}
    queue = list(paths)
    while queue:
        face = queue.pop(0)
        for k in range(len(sim.tried)):
            to, move = transition(sim, paths[face], k)
            if to == face:
                continue
            model[face, k] = (to, move)
            if to not in paths:
                paths[to] = (*paths[face], k)
                queue.append(to)
        print(f"# explored {face}: {len(paths)} faces so far", file=sys.stderr)
    return model, paths


def arrivals(model: Model, paths: dict[Face, Route], face: Face, count: int) -> list[Route]:
    """Up to ``count`` paths that leave the robot resting on ``face`` in different states:
    the first that reached it, then one by way of each other face the model says leads
    to it (each arrives from its own side, its cables in their own state)."""
    first = paths[face]
    out, sides = [first], {f for f, path in paths.items() if first and path == first[:-1]}
    for (f, k), (to, _) in sorted(model.items()):
        if len(out) >= count:
            break
        if to == face and f not in sides:
            out.append((*paths[f], k))
            sides.add(f)
    return out


def mean_move(moves: np.ndarray) -> np.ndarray:
    """The mean of planar moves (k, 3) (x, y in m, turn in rad): the turns' circular
    mean, so that turns of +179 and -179 degrees average to 180, not 0."""
    turn = np.arctan2(np.sin(moves[:, 2]).mean(), np.cos(moves[:, 2]).mean())
    return np.array([*moves[:, :2].mean(axis=0), turn])


def robust(
    sim: Rollouts, model: Model, paths: dict[Face, Route], starts: int, share: float
) -> Model:
    """The model's distinct outcomes (:func:`options`) run again from up to ``starts``
    resting states on their face (:func:`arrivals`): those that leave the robot on the
    same new face from at least ``share`` of them, each with its mean move there (a
    real robot, or a policy's corrections, never start a move from one state alone)."""
    kept: Model = {}
    for (face, to), ks in options(model).items():
        starts_ = [p for p in arrivals(model, paths, face, starts) if sim.outcome(p)[0] == face]
        held = 0
        for k in ks:
            landed = [m for t, m in (transition(sim, p, k) for p in starts_) if t == to]
            if landed and len(landed) >= share * len(starts_):
                kept[face, k] = (to, mean_move(np.array(landed)))
                held += 1
        print(f"# {face} -> {to}: {held} of {len(ks)} held", file=sys.stderr)
    return kept


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Planar moves (x, y, yaw) one after the other: ``b`` in ``a``'s end frame."""
    return np.array([*(a[:2] + rotated(b[:2], a[2])), a[2] + b[2]])


def options(
    model: Model,
) -> dict[tuple[Face, Face], list[int]]:
    """Per pair of faces, one candidate per distinct outcome (moves 0.1 m and 0.2 rad
    apart), the most common outcomes first, eight at most."""
    groups: dict[tuple[Face, Face], list[list[int]]] = {}
    for (face, k), (to, move) in model.items():
        clusters = groups.setdefault((face, to), [])
        for cluster in clusters:
            other = model[face, cluster[0]][1]
            if np.linalg.norm(other[:2] - move[:2]) < 0.1 and abs(other[2] - move[2]) < 0.2:
                cluster.append(k)
                break
        else:
            clusters.append([k])
    return {
        pair: [c[0] for c in sorted(cs, key=len, reverse=True)[:8]] for pair, cs in groups.items()
    }


def steering(sim: Rollouts, model: Model, per_pair: int) -> dict[str, Any]:
    """A steering gait's section: for every face, the ``per_pair`` most common distinct
    outcomes (:func:`options`) of every face it leads to, each with its move (CoM x, y in
    m in the face's frame, the yaw's change in rad) and the face it leaves the robot on,
    for FaceGait to choose from by the goal's direction."""
    d = sim.description
    actuated = [d.cables[int(k)].name for k in d.actuated]
    faces = []
    for (face, to), ks in sorted(options(model).items()):
        # A shuffle on the spot steers nowhere: it takes no place of the pair's.
        moving = [k for k in ks if float(np.linalg.norm(model[face, k][1][:2])) >= MIN_MOVE / 2]
        for k in moving[:per_pair]:
            move = model[face, k][1]
            faces.append(
                {
                    "face": [d.nodes[i].name for i in face],
                    "contract": [actuated[c] for c in sim.tried[k][0]],
                    "others": sim.tried[k][1],
                    "move": [round(float(v), 3) for v in move],
                    "to": [d.nodes[i].name for i in to],
                }
            )
    steps = {"hold_steps": sim.hold_steps, "settle_steps": sim.settle_steps}
    return {**steps, **({"ramp_steps": sim.ramp_steps} if sim.ramp_steps else {}), "faces": faces}


def steer_section(args: argparse.Namespace, sim: Rollouts) -> str:
    """The ``gaits: steer:`` section (YAML, under a comment that says how it was found)
    from the model of every face's transitions (:func:`explore`); closes ``sim``."""
    model, paths = explore(sim)
    section_ = steering(sim, robust(sim, model, paths, args.starts, args.share), args.per_pair)
    sim.close()
    flags = (
        f"--steer --max-combo {args.max_combo} --per-pair {args.per_pair} "
        f"--starts {args.starts} --share {args.share} --hold {args.hold} "
        f"--settle {args.settle} --ramp {args.ramp} --seeds {sim.seed}"
    )
    text = yaml.safe_dump(
        {"gaits": {"steer": section_}}, sort_keys=False, default_flow_style=None, width=100
    )
    return f"# steer: found by scripts/find_gait.py {args.robot} {flags}.\n{text}"


def turning_cycles(model: Model, sign: float, count: int) -> list[Table]:
    """The ``count`` cycles of faces (each once, 2 to 4) that the model says turn most
    the way of ``sign`` (+1: left) while they move: the turn (rad) times the CoM's move
    (m, at least MIN_MOVE) a gait period, the greatest first, as tables."""
    edges = options(model)
    faces = sorted({f for f, _ in edges})
    found: list[tuple[float, Table]] = []
    for n in range(2, min(len(faces), 4) + 1):
        for order in itertools.permutations(faces, n):
            pairs = list(zip(order, (*order[1:], order[0]), strict=True))
            if order[0] != min(order) or any(p not in edges for p in pairs):
                continue
            for ks in itertools.product(*(edges[p] for p in pairs)):
                move = np.zeros(3)
                for face, k in zip(order, ks, strict=True):
                    move = compose(move, model[face, k][1])
                turn = ((move[2] + np.pi) % (2.0 * np.pi) - np.pi) * sign / n
                speed = float(np.linalg.norm(move[:2])) / n
                if turn > 0 and speed >= MIN_MOVE:
                    found.append((turn * speed, dict(zip(order, ks, strict=True))))
    found.sort(key=lambda f: -f[0])
    return [table for _, table in found[:count]]


def closed_loop(args: argparse.Namespace, gait: Any, seed: int) -> dict[str, Any]:
    """Run ``gait`` (a FaceGait table; None: the robot's own forward gait) as FaceGait
    does for ``--steps`` control steps from ``reset(seed)``: what the true CoM did (m;
    "rest_path": its path from rest to rest, period to period; "first_pass": its move
    over as many periods as the table has faces) and how the robot turned
    (:func:`turning`)."""
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", robot=args.robot, estimator="oracle")
    inner = env.unwrapped
    d = inner.backend.description
    own = gait is None and d.gait is not None
    policy = FaceGait(
        d,
        inner.task,
        table=gait_table(d) if gait is None else gait,
        hold_steps=d.gait.hold_steps if own else args.hold,
        settle_steps=d.gait.settle_steps if own else args.settle,
        ramp_steps=d.gait.ramp_steps if own else args.ramp,
    )
    period = policy.hold_steps + policy.settle_steps
    obs, _ = env.reset(seed=seed)
    com, rests = [], []  # the true CoM after each step; face, yaw as each period starts
    for k in range(args.steps + 1):
        truth = inner.backend.ground_truth()
        com.append(truth.com[:2].copy())
        if k % period == 0:
            face = lowest_face(truth.node_positions)
            rests.append((face, face_yaw(truth.node_positions, face)))
        if k < args.steps:
            obs, *_ = env.step(policy(obs))
    env.close()
    path = np.array(com)
    travelled = np.cumsum(np.linalg.norm(np.diff(path[::period], axis=0), axis=1))
    reach = np.flatnonzero(travelled >= TRAVEL)
    return {
        "moved": path[-1] - path[0],
        "rest_path": float(travelled[-1]) if len(travelled) else 0.0,
        "steps_to_travel": (int(reach[0]) + 1) * period if reach.size else None,
        "first_pass": path[min(len(policy.table) * period, args.steps)] - path[0],
        **turning(path[::period], rests),
    }


def turning(points: np.ndarray, rests: list[tuple[Face, float]]) -> dict[str, float]:
    """How the robot turns (deg a gait period, left > 0) and how far its CoM goes (m a
    period), from one visit of its most visited support face to the next: its
    triangle's yaw, and the CoM (``points``, at the start of each period)."""
    faces = [f for f, _ in rests]
    face = max(set(faces[1:] or faces), key=faces.count)
    visits = [i for i, f in enumerate(faces) if f == face]
    if len(visits) < 2:
        return {"turn": 0.0, "speed": 0.0}
    yaw = np.unwrap([rests[i][1] for i in visits])
    periods = visits[-1] - visits[0]
    moves = np.linalg.norm(np.diff(points[visits], axis=0), axis=1)
    return {
        "turn": float(np.degrees(yaw[-1] - yaw[0])) / periods,
        "speed": float(moves.sum()) / periods,
    }


def measure(args: argparse.Namespace, sims: list[Rollouts], table: Table) -> list[dict[str, Any]]:
    """:func:`closed_loop` of the table on every seed."""
    gait = {face: sims[0].tried[k][:2] for face, k in table.items()}
    return [closed_loop(args, gait, sim.seed) for sim in sims]


def describe(args: argparse.Namespace, name: str, runs: list[dict[str, Any]], forward: Any) -> str:
    """The YAML comment that says what the gait does, on every seed."""
    flags = f"--turn {args.turn}" if args.turn else f"--direction {args.direction}"
    flags += f" --ramp {args.ramp}" if args.ramp else ""
    seeds = " ".join(map(str, args.seeds))
    lines = [
        f"# {name}: found by scripts/find_gait.py {args.robot} {flags} --seeds {seeds}.",
        f"# On the oracle, {args.steps} control steps from reset(seed); a period is "
        f"{args.hold + args.settle} steps; CoM path from rest to rest:",
    ]
    for seed, run, fwd in zip(args.seeds, runs, forward or [None] * len(runs), strict=True):
        reach = run["steps_to_travel"]
        text = (
            f"#   seed {seed}: {run['speed']:.2f} m and {run['turn']:+.1f} deg (left > 0) "
            f"a period, {np.linalg.norm(run['moved']):.2f} m from the start, "
            f"{run['rest_path']:.2f} m of path"
            + (f" ({TRAVEL:g} m in {reach} steps)" if reach else "")
        )
        if fwd is not None and name == "backward":
            text += f", cos {float(unit(run['moved']) @ unit(fwd['moved'])):+.2f} to forward's"
        lines.append(text)
    return "\n".join(lines)


def section(sim: Rollouts, table: Table, args: argparse.Namespace) -> dict[str, Any]:
    """The gait section as the YAML holds it, by names."""
    d = sim.description
    return {
        "hold_steps": args.hold,
        "settle_steps": args.settle,
        **({"ramp_steps": args.ramp} if args.ramp else {}),
        "faces": [
            {
                "face": [d.nodes[i].name for i in face],
                "contract": [d.cables[int(d.actuated[k])].name for k in sim.tried[c][0]],
                "others": sim.tried[c][1],
            }
            for face, c in table.items()
        ],
    }


def find(args: argparse.Namespace, sims: list[Rollouts], forward: Any) -> tuple[Table, list[Any]]:
    """The table for the objective, and its runs on every seed."""
    periods = args.steps // (args.hold + args.settle)
    if args.turn is None:
        body = None
        if args.direction == "backward":
            if forward is None:
                raise SystemExit(f"{args.robot} has no forward gait to go backward from")
            body = -rotated(unit(forward[0]["first_pass"]), -sims[0].yaw0)
        table = search(sims, {}, Heading(body), periods, args.restarts)
        return table, measure(args, sims, table)
    sign = 1.0 if args.turn == "left" else -1.0
    found = []
    for cycle in turning_cycles(explore(sims[0])[0], sign, args.candidates):
        table = search(sims, cycle, IntoTable(), periods, args.restarts)
        runs = measure(args, sims, table)
        worst = min(sign * r["turn"] * min(r["speed"], 1.0) for r in runs)
        print(f"# cycle {cycle}: {worst:+.2f} deg m a period^2 at worst", file=sys.stderr)
        found.append((worst, table, runs))
    _, table, runs = max(found, key=lambda f: f[0])
    return table, runs


def _steps(text: str) -> int:
    """A count of control steps (argparse type): an integer >= 0."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return int(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("robot")
    goal = parser.add_mutually_exclusive_group()
    goal.add_argument("--direction", choices=("forward", "backward"), default="forward")
    goal.add_argument("--turn", choices=("left", "right"), default=None)
    goal.add_argument(
        "--steer", action="store_true", help="every face's distinct transitions, to steer by"
    )
    parser.add_argument("--per-pair", type=int, default=2, help="--steer: outcomes per face pair")
    parser.add_argument(
        "--starts", type=int, default=3, help="--steer: resting states per face a move runs from"
    )
    parser.add_argument(
        "--share", type=float, default=0.6, help="--steer: share of --starts a move must hold in"
    )
    parser.add_argument("--candidates", type=int, default=6, help="turning cycles run")
    parser.add_argument("--max-combo", type=int, default=3)
    parser.add_argument("--hold", type=int, default=25, help="control steps of a contraction")
    parser.add_argument("--settle", type=int, default=10, help="control steps of the rest")
    parser.add_argument(
        "--ramp",
        type=_steps,
        default=None,
        help="control steps a command takes across the range (default: the robot gait's)",
    )
    parser.add_argument("--steps", type=int, default=600, help="control steps run in closed loop")
    parser.add_argument("--restarts", type=int, default=4, help="stalled entries struck at most")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--cache", default=None, help="JSON file of outcomes, read and written")
    args = parser.parse_args()
    if args.ramp is None:
        own = load_robot(args.robot).gait
        args.ramp = own.ramp_steps if own is not None else 0
    meta = {k: getattr(args, k) for k in ("robot", "hold", "settle", "ramp", "max_combo")}
    meta["version"] = CACHE_VERSION
    doc = (
        json.loads(Path(args.cache).read_text())
        if args.cache and Path(args.cache).is_file()
        else {}
    )
    cache = doc.get("outcomes", {}) if doc.get("meta") == meta else {}
    if args.steer:  # a model from the first seed's reset alone
        print(
            steer_section(
                args, Rollouts(args, args.seeds[0], cache.setdefault(str(args.seeds[0]), {}))
            )
        )
        if args.cache is not None:
            Path(args.cache).write_text(json.dumps({"meta": meta, "outcomes": cache}))
        return
    sims = [Rollouts(args, seed, cache.setdefault(str(seed), {})) for seed in args.seeds]
    has_gait = sims[0].description.gait is not None
    forward = [closed_loop(args, None, seed) for seed in args.seeds] if has_gait else None
    table, runs = find(args, sims, forward)
    for sim in sims:
        sim.close()
    if args.cache is not None:
        Path(args.cache).write_text(json.dumps({"meta": meta, "outcomes": cache}))
    name = args.turn or args.direction
    gait = section(sims[0], table, args)
    print(describe(args, name, runs, forward))
    out = {"gait": gait} if name == "forward" else {"gaits": {name: gait}}
    print(yaml.safe_dump(out, sort_keys=False, default_flow_style=None, width=100))


if __name__ == "__main__":
    main()
