"""The ICP tracker of Lu et al. 2022: its parts, and tracking the simulated 3-bar robot."""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import tensegrity_gym  # noqa: F401
from estimation.icp import IcpEstimator, IcpParams
from estimation.icp.observation import back_project, endcap_masks, fit_ground_plane, rod_hues
from estimation.metrics import rod_errors
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.kinematics import weighted_kabsch
from tensegrity_gym.model.samples import CableLengthSample, RgbdFrame
from tensegrity_gym.sim.backend import SimBackend
from tensegrity_gym.tasks.gaits import FaceGait


@pytest.fixture(scope="module")
def first_frame() -> tuple[SimBackend, RgbdFrame, np.random.Generator, list]:
    d = load_robot("three_bar")
    sim = SimBackend(d, camera=True)
    rng = np.random.default_rng(0)
    start = sim.reset(rng)
    [frame] = [s for s in start.samples if isinstance(s, RgbdFrame)]
    return sim, frame, rng, list(start.samples)


def test_weighted_kabsch_recovers_a_rigid_motion() -> None:
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=2).as_matrix()
    t = rng.normal(size=3)
    src = rng.normal(size=(40, 3))
    w = rng.uniform(0.1, 1.0, 40)
    dst = src @ R.T + t
    dst[:5] += 5.0  # outliers with zero weight do not move it
    w[:5] = 0.0
    R_hat, t_hat = weighted_kabsch(src, dst, w)
    assert np.allclose(R_hat, R, atol=1e-10) and np.allclose(t_hat, t, atol=1e-10)


def test_endcap_points_lie_on_their_endcaps(first_frame) -> None:
    sim, frame, _, _ = first_frame
    d = sim.description
    cal = sim.calibration
    masks = endcap_masks(frame.rgb, rod_hues(d))
    truth = sim.ground_truth()
    for k, (i, j) in enumerate(d.rod_nodes):
        assert masks[k].sum() >= 8, k  # each rod's endcaps are seen
        pts = back_project(frame.depth, cal.camera_intrinsics, cal.camera_pose, masks[k])
        near = np.minimum(
            np.linalg.norm(pts - truth.node_positions[i], axis=1),
            np.linalg.norm(pts - truth.node_positions[j], axis=1),
        )
        assert np.median(near) < d.rods[k].endcap_radius + 0.01
    assert not (masks[0] & masks[1]).any()  # colours do not overlap


def test_ground_plane_by_ransac(first_frame) -> None:
    sim, frame, rng, _ = first_frame
    cal = sim.calibration
    floor = ~endcap_masks(frame.rgb, rod_hues(sim.description)).any(axis=0)
    pts = back_project(frame.depth, cal.camera_intrinsics, cal.camera_pose, floor)
    n, offset = fit_ground_plane(pts[:: max(1, len(pts) // 3000)], np.random.default_rng(0))
    assert n[2] > 0.999 and abs(offset) < 0.005
    with pytest.raises(ValueError, match="cannot fix a plane"):
        fit_ground_plane(pts[:2], rng)


def _track(steps: int, params: IcpParams | None = None, seed: int = 0):
    d = load_robot("three_bar")
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", estimator=IcpEstimator(params))
    env.unwrapped.backend.camera = True
    obs, info = env.reset(seed=seed)
    gait = FaceGait(d, env.unwrapped.task)
    est, true, com = [], [], []
    for _ in range(steps):
        obs, _, _, _, info = env.step(gait(obs))
        est.append(env.unwrapped._estimate.node_positions)
        true.append(env.unwrapped.backend.ground_truth().node_positions)
        com.append(info["estimation_error"])
    reinit = env.unwrapped.estimator.reinitialisations
    env.close()
    return np.array(est), np.array(true), np.array(com), reinit, obs


def test_the_tracker_follows_the_rolling_robot() -> None:
    est, true, com, reinit, _ = _track(60)
    d = load_robot("three_bar")
    errors = rod_errors(est, true, d.rod_nodes)
    assert np.linalg.norm(true[-1].mean(0) - true[0].mean(0)) > 0.15  # it did roll
    assert errors.translation.mean() < 0.02
    assert np.degrees(errors.rotation.mean()) < 6.0
    assert com.mean() < 0.02 and reinit <= 1  # a loss, if any, is recovered from


def test_the_icp_env_is_repeatable_bit_for_bit() -> None:
    a = _track(8, seed=3)
    b = _track(8, seed=3)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[4], b[4])


def test_frames_without_depth_or_colour_keep_the_estimate_and_recover(first_frame) -> None:
    sim, frame, _, start = first_frame
    d = sim.description
    est = IcpEstimator()
    rng = np.random.default_rng(0)
    first = est.reset(d, sim.calibration, start, d.rest_lengths[d.actuated], rng)
    assert first.healthy
    blind = [
        replace(frame, t=0.1, depth=np.zeros_like(frame.depth)),  # camera unplugged
        replace(frame, t=0.2, rgb=np.zeros_like(frame.rgb)),  # no colour: no endcaps
    ]
    for f in blind:
        e = est.update([f], d.rest_lengths[d.actuated])
        assert e.is_finite() and not e.healthy
        assert np.allclose(e.node_positions, first.node_positions, atol=0.05)
    e = est.update([], d.rest_lengths[d.actuated])  # no frame at all this period
    assert e.is_finite() and not e.healthy
    back = est.update([replace(frame, t=0.3)], d.rest_lengths[d.actuated])
    assert back.healthy
    truth = sim.ground_truth().node_positions
    assert np.linalg.norm(back.node_positions - truth, axis=1).mean() < 0.03


def test_icp_is_a_registered_estimator_name() -> None:
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", estimator="icp")
    assert env.unwrapped.backend.camera  # frames are rendered only when asked
    _, info = env.reset(seed=0)
    assert info["estimation_error"] < 0.05
    env.close()
    with pytest.raises(ValueError, match="max_iterations"):
        IcpParams(max_iterations=0)


@pytest.mark.slow  # 26 s; the default run is near its 15 minutes
def test_the_icp_bench_scores_every_variant_of_table_1() -> None:
    from agents.benchmarks.icp import VARIANTS, bench_icp

    result = bench_icp(seeds=(0,), steps=12, env_steps=5)
    table = result["table"]
    assert set(VARIANTS) < set(table) and "measured (cable sensors)" in table
    for name in VARIANTS:
        row = table[name]
        assert 0.0 <= row["translation_cm"][0] < 10.0, name
        assert 0.0 <= row["within_2cm_5deg_percent"] <= 100.0
        assert row["ms_per_frame_median"] > 0.0
    assert table["measured (cable sensors)"]["shape_cm"][0] > 0.0
    assert result["env_speed"]["estimator"] == "icp"


def test_icp_runs_over_a_recorded_bag_and_refuses_one_without_frames(tmp_path, caplog) -> None:
    import json
    import logging

    from agents.cli import main

    assert (
        main(["record", "--estimator", "icp", "--steps", "25", "--out", str(tmp_path / "a")]) == 0
    )
    out = tmp_path / "est"
    assert (
        main(
            [
                "estimate",
                str(tmp_path / "a"),
                "--estimator",
                "icp",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["finite"] and metrics["com_rmse_m"] < 0.03
    assert (
        main(["record", "--estimator", "oracle", "--steps", "3", "--out", str(tmp_path / "b")]) == 0
    )
    with caplog.at_level(logging.ERROR):
        code = main(["estimate", str(tmp_path / "b"), "--estimator", "icp", "--out", str(out)])
    assert code == 2 and "needs rgbd (RGB-D camera frames)" in caplog.text


def test_rod_orientations_turn_about_their_axes_as_little_as_possible() -> None:
    """Section 4.2: each new orientation has the new axis and is the nearest to the old."""
    d = load_robot("three_bar")
    env = gym.make("tensegrity_gym/ThreeBarRoll-v0", estimator="icp")
    obs, _ = env.reset(seed=1)
    gait = FaceGait(d, env.unwrapped.task)
    quats, nodes = [], []
    for _ in range(40):
        obs, *_ = env.step(gait(obs))
        e = env.unwrapped._estimate
        quats.append(e.rod_quaternions)
        nodes.append(e.node_positions)
    env.close()
    R = Rotation.from_quat(np.concatenate(quats)).as_matrix().reshape(40, 3, 3, 3)
    x = np.array(nodes)
    axes = x[:, d.rod_nodes[:, 1]] - x[:, d.rod_nodes[:, 0]]
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    assert np.allclose(R[..., :, 2], axes, atol=1e-9)  # body z is the rod axis
    for k in range(39):
        for r in range(3):
            turn = np.degrees(Rotation.from_matrix(R[k, r].T @ R[k + 1, r]).magnitude())
            tilt = np.degrees(np.arccos(np.clip(axes[k, r] @ axes[k + 1, r], -1.0, 1.0)))
            assert abs(turn - tilt) < 1e-4  # no spin about the axis


def test_project_inverts_back_project(first_frame) -> None:
    from estimation.icp.observation import project

    sim, frame, _, _ = first_frame
    K, pose = sim.calibration.camera_intrinsics, sim.calibration.camera_pose
    mask = frame.depth > 0
    points = back_project(frame.depth, K, pose, mask)
    u, v, z = project(points, K, pose)
    rows, cols = np.nonzero(mask)
    np.testing.assert_allclose(u, cols + 0.5, atol=1e-6)
    np.testing.assert_allclose(v, rows + 0.5, atol=1e-6)
    np.testing.assert_allclose(z, frame.depth[mask], rtol=1e-6)


def _cropped(frame: RgbdFrame, columns: int) -> RgbdFrame:
    """The frame of a camera that sees only its first ``columns`` columns: the robot
    at its start, whose endcaps span columns 104-136, cut by the picture's edge."""
    return replace(frame, rgb=frame.rgb[:, :columns].copy(), depth=frame.depth[:, :columns].copy())


def test_a_robot_partly_out_of_view_is_not_placed_and_named_when_lost(first_frame) -> None:
    """A frame that cuts the robot places no rod (a partial view would place it wrong
    and lose it the next frame); a track lost while the picture cuts the robot is
    lost "out of view"."""
    from estimation.icp.tracker import IcpTracker

    sim, frame, _, start = first_frame
    d = sim.description
    truth = sim.ground_truth().node_positions
    tracker = IcpTracker(d, sim.calibration)
    cut = _cropped(frame, 120)
    assert tracker.out_of_view(truth, frame.rgb.shape[:2]) is None
    assert tracker.out_of_view(truth, cut.rgb.shape[:2]) is not None
    cables = next(s.lengths for s in start if isinstance(s, CableLengthSample))
    assert not tracker.initialise(cut, cables, np.random.default_rng(0))
    assert tracker.initialise(frame, cables, np.random.default_rng(0))
    tracker.nodes = tracker.nodes + np.array([0.5, 0.0, 0.0])  # the track slid away
    result = tracker.track(replace(cut, t=frame.t + 0.1), cables, np.random.default_rng(0))
    assert result.lost and result.cause == "out of view", result.reason


def test_drop_stray_points_keeps_an_endcap_and_drops_lone_points() -> None:
    from estimation.icp.observation import drop_stray_points

    rng = np.random.default_rng(3)
    cap = 0.0175 * Rotation.random(30, random_state=4).apply([0.0, 0.0, 1.0])  # on a sphere
    cap += rng.normal(0.0, 0.001, cap.shape)
    stray = np.array([[0.3, 0.0, -0.2], [0.31, 0.0, -0.2], [-0.4, 0.1, 0.0]])  # a pair, a lone
    points = np.vstack([cap, stray])
    kept = drop_stray_points(points, 0.035, 2)
    assert len(kept) == len(cap) and np.array_equal(kept, cap)
    assert len(drop_stray_points(points, 0.035, 0)) == len(points)  # 0 keeps every point
    assert len(drop_stray_points(np.zeros((0, 3)), 0.035, 2)) == 0


def _with_flying_pixels(frame: RgbdFrame, hues, per_rod: int) -> RgbdFrame:
    """``frame`` with ``per_rod`` pixels beside each rod's endcaps painted its colour
    while keeping the floor's depth behind them: the silhouette's edge of a real depth
    camera or an anti-aliased render, where colour and depth come from different
    surfaces."""
    rgb, depth = frame.rgb.copy(), frame.depth.copy()
    masks = endcap_masks(frame.rgb, hues)
    for mask in masks:
        rows, cols = np.nonzero(mask)
        colour = rgb[rows[0], cols[0]].copy()
        # pixels a little left of the rod's leftmost endcap pixel: the floor's depth
        for k in range(per_rod):
            r, c = rows[np.argmin(cols)] + k, cols.min() - 2
            rgb[r, c] = colour
    return replace(frame, rgb=rgb, depth=depth)


def test_flying_pixels_do_not_move_the_initialisation(first_frame) -> None:
    """Pixels of a rod's colour at the floor's depth (metres behind the endcap, seen
    from the camera) pulled the initialisation's endcaps tens of centimetres off on the
    other engine's frames; the stray-point filter keeps them out."""
    from estimation.icp.tracker import IcpTracker

    sim, frame, _, start = first_frame
    d = sim.description
    truth = sim.ground_truth().node_positions
    cables = next(s.lengths for s in start if isinstance(s, CableLengthSample))
    flying = _with_flying_pixels(frame, rod_hues(d), per_rod=2)

    def placed(params: IcpParams) -> float:
        tracker = IcpTracker(d, sim.calibration, params)
        assert tracker.initialise(flying, cables, np.random.default_rng(0))
        assert tracker.nodes is not None
        return float(np.linalg.norm(tracker.nodes - truth, axis=1).max())

    assert placed(IcpParams(stray_neighbours=0)) > 0.1  # the pixels do move it, unfiltered
    assert placed(IcpParams()) < 0.03


def test_a_cable_reading_shorter_than_the_endcaps_pulls_an_unseen_endcap_back(first_frame) -> None:
    """An endcap the camera does not see, swung off so that all its cables read more
    than ``cable_gate`` shorter than its distances, is pulled back by them: only a
    reading longer than the distance may be a slack cable's, and only such a one is
    left out of the correction."""
    from estimation.icp.tracker import IcpTracker

    sim, _, _, _ = first_frame
    d = sim.description
    truth = sim.ground_truth().node_positions
    cables = d.cable_nodes
    lengths = np.linalg.norm(truth[cables[:, 0]] - truth[cables[:, 1]], axis=1)
    i, j = d.rod_nodes[0]
    touching = np.flatnonzero((cables == i).any(axis=1))

    def swung(rotvec: np.ndarray) -> np.ndarray:
        hat = truth.copy()
        hat[i] = truth[j] + Rotation.from_rotvec(rotvec).apply(truth[i] - truth[j])
        return hat

    def shortest_excess(hat: np.ndarray) -> float:
        dist = np.linalg.norm(hat[cables[:, 0]] - hat[cables[:, 1]], axis=1)
        return float((dist - lengths)[touching].min())

    turns = [1.2 * axis for axis in Rotation.random(200, random_state=5).apply([1.0, 0.0, 0.0])]
    above = [t for t in turns if swung(t)[i, 2] > d.rods[0].endcap_radius]
    hat = swung(max(above, key=lambda t: shortest_excess(swung(t))))  # 36 cm off
    gate = IcpParams().cable_gate
    assert gate is not None and shortest_excess(hat) > gate  # a two-sided gate drops them all
    ratio = np.ones(d.n_nodes)
    ratio[i] = 0.0  # not seen: held by its cables
    tracker = IcpTracker(d, sim.calibration)
    corrected = hat
    errors = [float(np.linalg.norm(hat[i] - truth[i]))]
    for _ in range(IcpParams().max_iterations):  # a frame's rounds, no points seen for it
        corrected = tracker._correct(corrected, hat, ratio, lengths)
        errors.append(float(np.linalg.norm(corrected[i] - truth[i])))
    assert errors[1] < 0.8 * errors[0] and errors[-1] < 0.5 * errors[0], errors


def test_the_initialisation_holds_on_a_camera_with_flying_pixels() -> None:
    """The simulated camera with every pixel on a silhouette's edge reading between the
    endcap and the floor behind it (``CameraConfig.flying_pixels`` 1): unfiltered, such
    points put the rods a rod's length off; filtered, within centimetres."""
    from estimation.icp.tracker import IcpTracker

    d = load_robot("three_bar")
    camera = replace(d.sensors.camera, flying_pixels=1.0)
    d = replace(d, sensors=replace(d.sensors, camera=camera))
    sim = SimBackend(d, camera=True)
    errors: dict[int, list[float]] = {0: [], 2: []}
    try:
        for seed in range(3):
            start = sim.reset(np.random.default_rng(seed))
            [frame] = [s for s in start.samples if isinstance(s, RgbdFrame)]
            cables = next(s.lengths for s in start.samples if isinstance(s, CableLengthSample))
            truth = sim.ground_truth().node_positions
            for neighbours, found in errors.items():
                tracker = IcpTracker(d, sim.calibration, IcpParams(stray_neighbours=neighbours))
                assert tracker.initialise(frame, cables, np.random.default_rng(0))
                assert tracker.nodes is not None
                found.append(float(np.linalg.norm(tracker.nodes - truth, axis=1).max()))
    finally:
        sim.close()
    assert max(errors[0]) > 0.2  # the flying pixels do move an unfiltered one
    assert max(errors[2]) < 0.06 and np.mean(errors[2]) < 0.03, errors
