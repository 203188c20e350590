"""The window program's CVXPY specification (operators/slam/window_model.py) and the hand-compiled
program (window_program.py) are one program: windows captured from the SLAM on the real pipeline's
own AoAs and preintegrated IMU (one lap of `paper`, the run `lap_runs` makes), with and without
wheel odometry, solved both ways at the same tolerance, give the same optimum.

A window is compared where its optimum is unique: the objective's Hessian in the states x (prior,
wheel speeds, odometry edges, and the AoA rows in Huber's quadratic zone at the optimum; the split
variables n, t, h are then fixed by x) has no direction with less than `UNIQUE_MIN_INFO` of
information. A flatter direction would let two correct solvers part along it.
"""

from __future__ import annotations

import numpy as np
import pytest

from rover.formats.bag import BagReader
from rover.operators.slam.operator import Slam, SlamParams
from rover.operators.slam.window_model import TOLERANCE, WindowModel
from rover.operators.slam.window_program import Shape, UpdateData, WindowProgram, prior_indices, slot_columns
from rover.testing import run_operator

PREFIX_S = 30.0
"""the first seconds of the lap: the windows fill, tags are found, the window slides"""
EVERY = 4
"""every 4th captured solve is compared (all of them take a minute of CVXPY)"""
UNIQUE_MIN_INFO = 1e-6
"""smallest eigenvalue of the states' Hessian (1/m^2, (s/m)^2) for a unique optimum: a 1000 m std"""
OBJECTIVE_REL = 1e-6
STATES_M = 1e-4


def slam_inputs(run, seconds: float) -> dict[str, list]:
    """The SLAM's inputs in the run: its AoAs and odometry from results.mcap, the wheels from the dataset."""
    inputs: dict[str, list] = {"aoa": [], "odometry": [], "wheel": []}
    topics = {
        "/rover/aoa": ("aoa", "rover_msgs/msg/Aoa"),
        "/rover/preintegration": ("odometry", "rover_msgs/msg/Preintegration"),
    }
    with BagReader(run.output / "results.mcap") as bag:
        start = None
        for m in bag.messages(topics):
            start = m.log_time_ns if start is None else start
            if m.log_time_ns - start <= seconds * 1e9:
                port, typename = topics[m.topic]
                inputs[port].append(bag.decode(m, typename))
    assert start is not None, "the run recorded no AoA"
    with BagReader(run.dataset) as bag:
        for m in bag.messages(["/odom"]):
            if m.log_time_ns - start <= seconds * 1e9:
                inputs["wheel"].append(bag.decode(m, "nav_msgs/msg/Odometry"))
    return inputs


@pytest.fixture(scope="module")
def windows(lap_runs) -> list[tuple[Shape, UpdateData]]:
    run = lap_runs["with"]
    assert run.status == 0, run.stderr
    inputs = slam_inputs(run, PREFIX_S)
    captured: list[tuple[Shape, UpdateData]] = []
    solve = WindowProgram.solve

    def spy(self: WindowProgram, d: UpdateData) -> tuple[np.ndarray, int]:
        captured.append((self.shape, d))
        return solve(self, d)

    WindowProgram.solve = spy  # type: ignore[method-assign]
    try:
        for wheel in (True, False):
            run_operator(Slam(SlamParams(wheel=wheel)), inputs)
    finally:
        WindowProgram.solve = solve  # type: ignore[method-assign]
    return captured[::EVERY]


def hessian(shape: Shape, d: UpdateData, x: np.ndarray) -> np.ndarray:
    """The objective's Hessian in x at x (the Huber rows beyond M are linear there)."""
    h = np.zeros((shape.states, shape.states))
    prior = prior_indices(shape)
    h[np.ix_(prior, prior)] += d.prior_info
    for k, info in enumerate(d.velocity_info):
        h[4 * k + 2 : 4 * k + 4, 4 * k + 2 : 4 * k + 4] += info
    for e, (lmat, chol) in enumerate(zip(d.edge_l, d.edge_chol, strict=True)):
        span = np.arange(4 * e, 4 * e + 8)
        h[np.ix_(span, span)] += lmat.T @ np.linalg.solve(chol @ chol.T, lmat)
    columns = slot_columns(shape)
    rows = np.zeros((shape.rows, shape.states))
    np.add.at(rows, (np.arange(shape.rows)[:, None], columns), d.a)
    quadratic = np.abs(rows @ x + d.offset) < d.huber_m
    return h + rows[quadratic].T @ rows[quadratic]


def test_the_model_is_dpp_and_reused_for_its_shape():
    shape = Shape(epochs=3, slots=2, tags=2)
    model = WindowModel(shape)
    assert model.problem.is_dpp()
    assert {p.name() for p in model.problem.parameters()} >= {"R", "c", "dt", "delta", "k", "M", "w"}


def test_every_captured_window_has_the_same_optimum_both_ways(windows):
    assert len(windows) >= 100, len(windows)
    compiled: dict[Shape, WindowProgram] = {}
    models: dict[Shape, WindowModel] = {}
    unique = 0
    shapes = set()
    for shape, d in windows:
        program = compiled.setdefault(shape, WindowProgram(shape, max_iter=200, tolerance=TOLERANCE))
        model = models.setdefault(shape, WindowModel(shape))
        x_compiled, _ = program.solve(d)
        x_model, _ = model.solve(d)
        if np.linalg.eigvalsh(hessian(shape, d, x_compiled))[0] < UNIQUE_MIN_INFO:
            continue
        unique += 1
        shapes.add(shape)
        scale = max(1.0, abs(program.objective))
        gap = abs(model.objective - program.objective)
        assert gap <= OBJECTIVE_REL * scale, (shape, model.objective, program.objective)
        assert np.max(np.abs(x_model - x_compiled)) <= STATES_M, (shape, np.max(np.abs(x_model - x_compiled)))
    assert unique >= 0.8 * len(windows), f"only {unique} of {len(windows)} windows have a unique optimum"
    assert len(shapes) >= 5, shapes  # windows filling, sliding, with tags found on the way


def test_batch_mode_solves_with_the_model(lap_runs):
    inputs = slam_inputs(lap_runs["with"], 10.0)
    solved: list[Shape] = []
    solve = WindowModel.solve

    def spy(self: WindowModel, d: UpdateData) -> tuple[np.ndarray, int]:
        solved.append(self.shape)
        return solve(self, d)

    WindowModel.solve = spy  # type: ignore[method-assign]
    try:
        out = run_operator(Slam(SlamParams(batch=True)), inputs)
    finally:
        WindowModel.solve = solve  # type: ignore[method-assign]
    assert solved and len({s.epochs for s in solved}) == 1  # one window holding the whole run
    final = [e for e in out if e.port == "trajectory"]
    assert len(final) == solved[0].epochs
