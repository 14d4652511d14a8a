"""The estimation benchmark: the study of Caluwaerts et al. 2016 in simulation, and the filter's
speed.

Accuracy: SUPERball is recorded once per seed during a face transition (the scripted
gait) and once during stationary actuation (two actuators on phase-shifted stepwise
sines, Caluwaerts et al. 2016 section V-A); every filter variant of the paper's study then runs on
the same samples. The 3-bar robot, rolling, is scored with the full filter too.

Speed: the same filter steps (predict over one control period, then update) run
through this project's UKF and through filterpy's ``UnscentedKalmanFilter`` on the same
model and the same measurements, side by side in one process. filterpy calls its
process model once per sigma point; it is timed twice, with the model as this project
compiles it (numba) and with the same equations in plain numpy, the way a model is
written for filterpy (:func:`propagate_numpy`, here: benchmark code, not the filter's).
"""

from __future__ import annotations

import logging
import time
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np

from agents.recordings.runs import RecordedRun, record_run, replay, trajectory_errors
from estimation.ukf import UkfConfig, UkfEstimator
from estimation.ukf.filter import single_threaded_blas
from tensegrity_gym.model.description import DEFAULT_GAIT
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from numpy.typing import NDArray

    from agents.training.cluster import Executor
    from estimation.ukf.estimator import FilterStep
    from estimation.ukf.spring_mass import KernelArrays
    from tensegrity_gym.envs.tensegrity_env import TensegrityEnv

__all__ = [
    "VARIANTS",
    "bench_estimation",
    "bench_filter_speed",
    "propagate_numpy",
    "record_face_transition",
    "record_stationary_actuation",
]

log = logging.getLogger(__name__)

VARIANTS: dict[str, UkfConfig] = {
    "full": UkfConfig(),
    "no IMU": UkfConfig(use_imu=False),
    "constant offset": UkfConfig(constant_offset=True),
    "4 of 8 anchors": UkfConfig(anchors=(0, 2, 4, 6)),
}
"""The settings of Caluwaerts et al. 2016 fig. 7-8."""


def _gait_policy(name: str = DEFAULT_GAIT) -> Any:
    gait: FaceGait | None = None

    def policy(env: TensegrityEnv, obs: NDArray[np.float32], step: int) -> NDArray[np.float32]:
        nonlocal gait
        if gait is None:
            gait = FaceGait(env.backend.description, env.task, gait=name)
        return gait(obs)

    return policy


def record_face_transition(
    env_id: str, seed: int, steps: int = 200, gait: str = DEFAULT_GAIT, **make_kwargs: Any
) -> RecordedRun:
    """The robot rolls face to face under its scripted gait ``gait`` (``make_kwargs``:
    more arguments of ``gym.make``, and ``record_run``'s ``camera``)."""
    return record_run(env_id, _gait_policy(gait), steps, seed, **make_kwargs)


def record_stationary_actuation(
    env_id: str,
    seed: int,
    steps: int = 200,
    cables: tuple[int, int] = (0, 1),
    **make_kwargs: Any,
) -> RecordedRun:
    """The robot stays on its face while two actuated cables follow phase-shifted
    stepwise sines (a new level every second, period 8 s, a quarter of the motor range).
    """

    def policy(env: TensegrityEnv, obs: NDArray[np.float32], step: int) -> NDArray[np.float32]:
        d = env.backend.description
        hold = env.targets_to_action(d.rest_lengths[d.actuated])
        t = np.floor(step * env.backend.control_period)  # seconds, held for a second
        for k, phase in zip(cables, (0.0, 0.5 * np.pi), strict=True):
            hold[k] = np.clip(hold[k] - 0.25 + 0.25 * np.sin(2 * np.pi * t / 8.0 + phase), -1, 1)
        return hold

    return record_run(env_id, policy, steps, seed, **make_kwargs)


def _score(run: RecordedRun, config: UkfConfig) -> dict[str, Any]:
    estimator = UkfEstimator(config)
    out = trajectory_errors(run, replay(run, estimator))
    diag = estimator.diagnostics
    out["rows_rejected_share"] = round(diag.rejected_rows / max(diag.rows, 1), 4)
    return out


def _mean_rows(rows: list[dict[str, Any]]) -> dict[str, Any]:
    keys = (
        "com_rmse_m", "com_max_m", "node_rmse_m", "node_max_m", "rod_translation_mean_m",
        "rod_rotation_mean_deg", "rods_within_2cm_5deg", "shape_error_mean_m",
        "rows_rejected_share",
    )  # fmt: skip
    out: dict[str, Any] = {k: round(float(np.mean([r[k] for r in rows])), 4) for k in keys}
    out["reinitialisations"] = int(sum(r["reinitialisations"] for r in rows))
    out["all_finite"] = bool(all(r["finite"] for r in rows))
    out["runs"] = len(rows)
    return out


_SCENARIOS: dict[str, Callable[..., RecordedRun]] = {
    "face transition": record_face_transition,
    "stationary actuation": record_stationary_actuation,
}
"""The recordings of the study, by scenario."""


def _record_job(steps: int, job: tuple[str, str, int]) -> RecordedRun:
    """One recording of the study, ``job`` = (scenario, env id, seed)."""
    scenario, env_id, seed = job
    return _SCENARIOS[scenario](env_id, seed, steps)


def _score_job(runs: Sequence[RecordedRun], job: tuple[int, str]) -> dict[str, Any]:
    """One replay of the study, ``job`` = (index into ``runs``, variant)."""
    return _score(runs[job[0]], VARIANTS[job[1]])


def bench_estimation(
    seeds: tuple[int, ...] = (0, 1, 2), steps: int = 200, executor: Executor | None = None
) -> dict[str, Any]:
    """The accuracy table: scenario x variant, errors averaged over ``seeds``. The
    recordings, then the replays, are jobs of ``executor`` (default: here, one after
    the other; :class:`agents.training.cluster.RayExecutor`: Ray tasks, the same numbers)."""
    from agents.training.cluster import LocalExecutor

    jobs = executor or LocalExecutor()
    superball, three_bar = "tensegrity_gym/SuperBallRoll-v0", "tensegrity_gym/ThreeBarRoll-v0"
    recordings = [(scenario, superball, seed) for scenario in _SCENARIOS for seed in seeds]
    recordings += [("face transition", three_bar, seed) for seed in seeds]
    runs = jobs.map(partial(_record_job, steps), recordings)

    def indices(scenario: str, env_id: str) -> list[int]:
        return [i for i, r in enumerate(recordings) if r[:2] == (scenario, env_id)]

    rows = [  # (robot, scenario, variant, the indices of its runs)
        ("superball", scenario, variant, indices(scenario, superball))
        for scenario in _SCENARIOS
        for variant in VARIANTS
    ]
    rows.append(("three_bar", "face transition", "full", indices("face transition", three_bar)))
    replays = [(i, variant) for _, _, variant, runs_of in rows for i in runs_of]
    scores = iter(jobs.map(partial(_score_job, runs), replays))
    table: list[dict[str, Any]] = []
    for robot, scenario, variant, runs_of in rows:
        scored = [next(scores) for _ in runs_of]
        table.append(
            {"robot": robot, "scenario": scenario, "variant": variant} | _mean_rows(scored)
        )
        log.info("%s / %s / %s: %s", robot, scenario, variant, table[-1])
    return {
        "settle_s": 2.0,
        "seconds_per_run": steps * 0.1,
        "table": table,
        "targets": {"superball full, rolling: com_rmse_m": 0.05, "node_rmse_m": 0.10},
    }


def _ramp_np(x: NDArray[np.float64], width: float) -> NDArray[np.float64]:
    """The model's rounded max(0, x), elementwise (estimation.ukf.spring_mass._ramp)."""
    u = np.clip(x + width, 0.0, 2.0 * width)
    return np.where(x >= width, x, u * u / (4.0 * width))


def _step_np(x: NDArray[np.float64], width: float) -> NDArray[np.float64]:
    """The slope of :func:`_ramp_np`."""
    return np.clip((x + width) / (2.0 * width), 0.0, 1.0)


def _member_forces_np(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    rest: NDArray[np.float64],
    members: NDArray[np.int64],
    member_params: NDArray[np.float64],
    smooth: float,
) -> NDArray[np.float64]:
    """What every member pulls on its first node, (S, M, 3) (N), for positions and
    velocities ``x``, ``v`` (S, n, 3) and rest lengths ``rest`` (1 or S, M) (m)."""
    i, j, cable = members[:, 0], members[:, 1], members[:, 2] != 0
    stiffness, damping = member_params[:, 0], member_params[:, 1]
    u = x[:, j] - x[:, i]
    length = np.linalg.norm(u, axis=-1)
    rate = np.einsum("smi,smi->sm", u, v[:, j] - v[:, i]) / length
    stretch = length - rest
    tension = np.where(
        cable,
        np.maximum(
            stiffness * _ramp_np(stretch, smooth) + damping * rate * _step_np(stretch, smooth),
            0.0,
        ),
        stiffness * stretch + damping * rate,
    )
    return np.asarray((tension / length)[..., None] * u)


def _segments_closest_np(
    d1: NDArray[np.float64], d2: NDArray[np.float64], r: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(s, t) (S, P) of the closest points of segments a0 + s d1 and b0 + t d2, with
    ``r`` = a0 - b0, all (S, P, 3) (estimation.ukf.spring_mass._segments_closest)."""
    aa, ee = np.einsum("spi,spi->sp", d1, d1), np.einsum("spi,spi->sp", d2, d2)
    f, cc = np.einsum("spi,spi->sp", d2, r), np.einsum("spi,spi->sp", d1, r)
    bb = np.einsum("spi,spi->sp", d1, d2)
    denom = aa * ee - bb * bb
    s = np.where(
        denom > 1e-12 * aa * ee,
        np.clip((bb * f - cc * ee) / np.where(denom > 0, denom, 1.0), 0.0, 1.0),
        0.0,
    )
    t = (bb * s + f) / ee
    s = np.where(
        t < 0.0,
        np.clip(-cc / aa, 0.0, 1.0),
        np.where(t > 1.0, np.clip((bb - cc) / aa, 0.0, 1.0), s),
    )
    return s, np.clip(t, 0.0, 1.0)


def _deepest_touch_np(
    x: NDArray[np.float64], arrays: KernelArrays
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(depth (m), s, t), each (S, P), of every rod pair's deepest overlap, tried in the
    kernel's order (estimation.ukf.spring_mass._deepest_touch)."""
    a0, a1, b0, b1 = arrays.pairs.T
    pa, pb = x[:, a0], x[:, b0]
    d1, d2 = x[:, a1] - pa, x[:, b1] - pb

    def on(
        p: NDArray[np.float64], q0: NDArray[np.float64], d: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """t (S, P) of the point of segment q0 + t d closest to p."""
        t = np.einsum("spi,spi->sp", p - q0, d) / np.einsum("spi,spi->sp", d, d)
        return np.asarray(np.clip(t, 0.0, 1.0))

    s, t = _segments_closest_np(d1, d2, pa - pb)
    ones = np.ones_like(s)
    tried = [(s, t, 0)]  # (s, t, column of pair_params)
    for end in (0.0, 1.0):
        tried.append((end * ones, on(pa + end * d1, pb, d2), 1))
        tried += [(end * ones, other * ones, 3) for other in (0.0, 1.0)]
    tried += [(on(pb + end * d2, pa, d1), end * ones, 2) for end in (0.0, 1.0)]
    ss = np.stack([c[0] for c in tried])
    ts = np.stack([c[1] for c in tried])
    gap = pa + ss[..., None] * d1 - pb - ts[..., None] * d2
    reach = np.stack([arrays.pair_params[:, c[2]] for c in tried])[:, None, :]
    depth = reach - np.linalg.norm(gap, axis=-1)
    best = np.argmax(depth, axis=0)[None]  # the first of equal depths, as the kernel
    depth, ss, ts = (np.take_along_axis(a, best, axis=0)[0] for a in (depth, ss, ts))
    return depth, ss, ts


def _pair_forces_np(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    by_node: NDArray[np.float64],
    arrays: KernelArrays,
) -> None:
    """Adds the rod-rod contact forces to ``by_node`` (n, S, 3) (N), from positions and
    velocities ``x``, ``v`` (S, n, 3)."""
    _, _, _, _, _, smooth, contact_k, contact_c = arrays.constants
    a0, a1, b0, b1 = arrays.pairs.T
    depth, s, t = _deepest_touch_np(x, arrays)
    sv, tv = s[..., None], t[..., None]
    gap = x[:, a0] + sv * (x[:, a1] - x[:, a0]) - x[:, b0] - tv * (x[:, b1] - x[:, b0])
    dist = np.linalg.norm(gap, axis=-1)
    centre = 0.5 * (x[:, a0] + x[:, a1] - x[:, b0] - x[:, b1])
    near = (
        (np.einsum("spi,spi->sp", centre, centre) <= arrays.pair_params[:, 4])
        & (dist >= 1e-9)
        & (depth > -smooth)
    )
    normal = gap / np.where(dist > 0, dist, 1.0)[..., None]
    rel = np.einsum(
        "spi,spi->sp",
        (1 - sv) * v[:, a0] + sv * v[:, a1] - (1 - tv) * v[:, b0] - tv * v[:, b1],
        normal,
    )
    fn = contact_k * _ramp_np(depth, smooth) - contact_c * rel * _step_np(depth, smooth)
    push = np.where(near & (fn > 0.0), fn, 0.0)[..., None] * normal
    for nodes, share in ((a0, (1 - sv) * push), (a1, sv * push)):
        np.add.at(by_node, nodes, share.transpose(1, 0, 2))
    for nodes, share in ((b0, (1 - tv) * push), (b1, tv * push)):
        np.add.at(by_node, nodes, -share.transpose(1, 0, 2))


def propagate_numpy(
    states: NDArray[np.float64],
    n_steps: int,
    h: float,
    rest: NDArray[np.float64],
    arrays: KernelArrays,
) -> None:
    """The model's equations (a ``estimation.ukf.spring_mass.Kernel``) in plain numpy,
    vectorised over states, members and rod pairs: what a model written for filterpy
    would be.

    Advances ``states`` (S, 6 n) in place by ``n_steps`` substeps of ``h`` seconds,
    ``rest`` (R, 2, M) the members' rest lengths (m) at the start and end, of every
    state (R = 1) or of each (R = S).
    """
    S, n = states.shape[0], arrays.nodes.shape[0]
    x = states[:, : 3 * n].reshape(S, n, 3)
    v = states[:, 3 * n :].reshape(S, n, 3)
    i, j = arrays.members[:, 0], arrays.members[:, 1]
    inv_mass, ground_height = arrays.nodes[:, 0], arrays.nodes[:, 1]
    gravity, ground_k, ground_c, mu, slip, smooth, _, _ = arrays.constants
    for step in range(n_steps):
        rest_now = rest[:, 0] + (step + 0.5) / n_steps * (rest[:, 1] - rest[:, 0])
        pull = _member_forces_np(x, v, rest_now, arrays.members, arrays.member_params, smooth)
        force = np.zeros_like(x)
        by_node = force.transpose(1, 0, 2)  # a view, (n, S, 3): np.add.at on the node axis
        np.add.at(by_node, i, pull.transpose(1, 0, 2))
        np.add.at(by_node, j, -pull.transpose(1, 0, 2))
        if len(arrays.pairs):
            _pair_forces_np(x, v, by_node, arrays)
        depth = ground_height - x[..., 2]
        fn = ground_k * _ramp_np(depth, smooth) - ground_c * v[..., 2] * _step_np(depth, smooth)
        fn = np.maximum(fn, 0.0)
        v += h * inv_mass[:, None] * force
        v[..., 2] += h * (inv_mass * fn - gravity)
        speed = np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + slip * slip)
        scale = 1.0 / (1.0 + h * inv_mass * mu * fn / speed)
        v[..., 0] *= scale
        v[..., 1] *= scale
        x += h * v


def _filterpy_ukf(x: NDArray[np.float64], P: NDArray[np.float64], config: UkfConfig) -> Any:
    from filterpy.kalman import MerweScaledSigmaPoints
    from filterpy.kalman import UnscentedKalmanFilter as FilterpyUKF

    n = x.shape[0]
    sp = config.sigma_points
    points = MerweScaledSigmaPoints(n, sp.alpha, sp.beta, sp.kappa)
    ukf = FilterpyUKF(n, 1, 0.1, hx=None, fx=None, points=points)
    ukf.x, ukf.P = x.copy(), P.copy()
    return ukf


def _filterpy_step(
    estimator: UkfEstimator,
    prepared: FilterStep,
    x0: NDArray[np.float64],
    P0: NDArray[np.float64],
    compiled: bool,
) -> tuple[float, NDArray[np.float64]]:
    """filterpy's predict-update of ``prepared`` from mean ``x0`` (d,) and covariance
    ``P0`` (d, d), on the estimator's model (its compiled kernel, or plain numpy) and
    measurements: milliseconds it took, and its mean (d,) after. filterpy calls fx and
    hx once per sigma point."""
    measurements, batch = estimator.measurements, prepared.batch

    def hx(state: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(measurements.predict(batch, state[None])[0])

    def fx(state: NDArray[np.float64], dt: float) -> NDArray[np.float64]:
        return estimator.propagate(state, prepared, None if compiled else propagate_numpy)

    ref = _filterpy_ukf(x0, P0, estimator.config)
    q = prepared.process_noise
    ref.Q = np.diag(q) if q.ndim == 1 else q
    t0 = time.perf_counter()
    ref.predict(dt=prepared.duration, fx=fx)
    ref.update(batch.z, R=np.diag(batch.variance), hx=hx)
    return 1e3 * (time.perf_counter() - t0), np.asarray(ref.x)


def bench_filter_speed(
    env_id: str, seed: int = 0, steps: int = 40, numpy_steps: int = 5
) -> dict[str, Any]:
    """Milliseconds a filter step, this project's UKF and filterpy's, same model and data.

    The run is recorded with the gait; each step's inputs are prepared once, then the
    same predict-update is timed on both filters from the same mean and covariance.
    """
    run = record_face_transition(env_id, seed, steps + 10)
    # Without the gate, so that both filters use every row and their states agree.
    estimator = UkfEstimator(UkfConfig(gate_probability=None))
    rng = np.random.default_rng(seed)
    estimator.reset(run.description, run.calibration, run.start.samples, run.start.command, rng)
    fast_ms: list[float] = []
    filterpy_ms: list[float] = []
    filterpy_numpy_ms: list[float] = []
    full_update_ms: list[float] = []
    max_state_diff = 0.0
    with single_threaded_blas():
        for step in run.steps[:steps]:
            t0 = time.perf_counter()
            prepared = estimator.prepare(step.samples, step.command)
            prepare_s = time.perf_counter() - t0
            x0, P0 = estimator.filter.x.copy(), estimator.filter.P.copy()

            t0 = time.perf_counter()
            estimator.apply(prepared, estimator.filter)
            fast = time.perf_counter() - t0
            fast_ms.append(1e3 * fast)
            full_update_ms.append(1e3 * (fast + prepare_s))

            # filterpy once with the same compiled kernel, and (on the first few steps)
            # with the model in plain numpy.
            for compiled, times in ((True, filterpy_ms), (False, filterpy_numpy_ms)):
                if not compiled and len(times) >= numpy_steps:
                    continue
                ms, x = _filterpy_step(estimator, prepared, x0, P0, compiled)
                times.append(ms)
                max_state_diff = max(max_state_diff, float(np.max(np.abs(x - estimator.filter.x))))
    fast_med, ref_med = float(np.median(fast_ms)), float(np.median(filterpy_ms))
    numpy_med = float(np.median(filterpy_numpy_ms))
    d = run.description
    return {
        "robot": d.name,
        "state_dim": len(estimator.filter.x),
        "sigma_points": 2 * len(estimator.filter.x) + 1,
        "steps_timed": len(fast_ms),
        "fast_filter_step_ms_median": round(fast_med, 3),
        "fast_estimator_update_ms_median": round(float(np.median(full_update_ms)), 3),
        "filterpy_compiled_model_ms_median": round(ref_med, 3),
        "speedup_vs_filterpy_compiled_model": round(ref_med / fast_med, 1),
        "filterpy_numpy_model_ms_median": round(numpy_med, 3),
        "speedup_vs_filterpy_numpy_model": round(numpy_med / fast_med, 1),
        "max_state_difference_vs_filterpy_m": float(f"{max_state_diff:.3g}"),
    }
