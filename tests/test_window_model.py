"""The window program's CVXPY specification (operators/slam/window_model.py) and the hand-compiled
program (window_program.py) are one program: windows captured from the SLAM on the real pipeline's
own AoAs and preintegrated IMU (one lap of `paper`, the run `lap_runs` makes), with and without
wheel odometry, solved both ways at the same tolerance, give the same optimum.

A window is compared where its optimum is unique: the objective's Hessian H in the states x (prior,
wheel speeds, odometry edges, and the AoA rows in Huber's quadratic zone at the optimum; the split
variables n, t, h are then fixed by x) has no direction with less than `UNIQUE_MIN_INFO` of
information: H - UNIQUE_MIN_INFO I has a Cholesky factor (Cholesky stays accurate across the
window's 1e12 spread of scales, where an eigen-solver's smallest eigenvalue drowns in rounding).
A flatter direction would let two correct solvers part along it. The run's windows never reach
Huber's linear zone, so windows of a synthetic scene with 20% outlier bearings (tests/slam_scenes.py)
are compared too; each set must exercise the term it is there for.
"""

from __future__ import annotations

import numpy as np
import pytest
from slam_windows import EVERY, hessian, lap_windows, outlier_windows, rows_at, slam_inputs, unheard_tag_states, unique

from rover.operators.slam.layout import Shape
from rover.operators.slam.operator import Slam, SlamParams
from rover.operators.slam.window_model import TOLERANCE, WindowModel
from rover.operators.slam.window_program import UpdateData, WindowProgram
from rover.testing import run_operator

OBJECTIVE_REL = 1e-6
STATES_M = 1e-4


@pytest.fixture(scope="module")
def windows(lap_runs) -> list[tuple[Shape, UpdateData]]:
    return lap_windows(lap_runs["with"])[::EVERY]


def test_the_model_is_dpp_and_reused_for_its_shape():
    shape = Shape(epochs=3, slots=2, tags=2, biases=4)
    model = WindowModel(shape)
    assert model.problem.is_dpp()
    assert {p.name() for p in model.problem.parameters()} >= {"R", "c", "dt", "delta", "k", "M", "w"}


def compare(windows: list[tuple[Shape, UpdateData]]) -> dict[str, int]:
    """Solve each window both ways; assert the same optimum where it is unique; count what was compared
    and which terms were active there."""
    compiled: dict[Shape, WindowProgram] = {}
    models: dict[Shape, WindowModel] = {}
    seen = {"windows": 0, "unique": 0, "shapes": 0, "huber_linear": 0, "hinge": 0}
    shapes = set()
    for shape, d in windows:
        program = compiled.setdefault(shape, WindowProgram(shape, max_iter=200, tolerance=TOLERANCE))
        model = models.setdefault(shape, WindowModel(shape))
        x_compiled, _ = program.solve(d)
        x_model, _ = model.solve(d)
        seen["windows"] += 1
        if not unique(hessian(shape, d, x_compiled)):
            continue
        seen["unique"] += 1
        shapes.add(shape)
        gap = abs(model.objective - program.objective)
        assert gap <= OBJECTIVE_REL * max(1.0, abs(program.objective)), (shape, model.objective, program.objective)
        dx = x_model - x_compiled
        waiting = unheard_tag_states(shape, d)
        assert np.max(np.abs(dx[~waiting]), initial=0.0) <= STATES_M, (shape, np.max(np.abs(dx[~waiting])))
        h = hessian(shape, d, x_compiled)[np.ix_(waiting, waiting)]
        assert 0.5 * dx[waiting] @ h @ dx[waiting] <= OBJECTIVE_REL * max(1.0, abs(program.objective)), shape
        residual = rows_at(shape, d.a) @ x_compiled + d.offset
        seen["huber_linear"] += bool(np.any(np.abs(residual) > d.huber_m))
        seen["hinge"] += bool(np.any((rows_at(shape, d.g) @ x_compiled < 0) & (d.hinge > 0)))
    seen["shapes"] = len(shapes)
    return seen


@pytest.mark.slow
def test_every_captured_window_has_the_same_optimum_both_ways(windows):
    seen = compare(windows)
    assert seen["windows"] >= 100, seen
    assert seen["unique"] >= 0.8 * seen["windows"], f"too few windows with a unique optimum: {seen}"
    assert seen["shapes"] >= 5, seen  # windows filling, sliding, with tags found on the way
    # the wheel run's windows hold the wheel scale state, coupled to the velocities by the wheel speed
    assert any(shape.scale and np.any(d.velocity_info[:, :2, 2]) for shape, d in windows)


def test_windows_with_outlier_bearings_have_the_same_optimum_both_ways():
    seen = compare(outlier_windows())
    assert seen["unique"] >= 0.8 * seen["windows"], seen
    assert seen["huber_linear"] > 0, seen  # rows in Huber's linear zone were compared
    assert seen["hinge"] > 0, seen  # and rows whose cheirality hinge was active


@pytest.mark.slow
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
