"""The Gauss-Newton step's direct solve (operators/slam/gauss_newton.py) finds the optimum the compiled
program finds with Clarabel at the specification's tight tolerance, on the windows the SLAM solves:
those of the real pipeline's AoAs and IMU (which seldom leave Huber's quadratic zone) and those of a
scene with 20% outlier bearings (which reach its linear zone, so that the zones take more than one
solve to settle); and it declines, leaving the step to the program, where the optimum is not unique."""

from __future__ import annotations

import numpy as np
import pytest
from slam_scenes import INDEPENDENT_BURSTS, angles, estimate, scene
from slam_windows import EVERY, hessian, lap_windows, outlier_windows, rows_at, unique

from rover.operators.slam.gauss_newton import DirectStep
from rover.operators.slam.layout import Shape
from rover.operators.slam.sliding_window import WindowSettings
from rover.operators.slam.window_model import TOLERANCE
from rover.operators.slam.window_program import UpdateData, WindowProgram, edge_matrix

STATES_M = 1e-5
"""the two solutions' largest difference in any state (m, m/s): a state the window holds loosely (a
tag seen only by bearings far beyond Huber's threshold, a std of metres) is where the program's
tolerance leaves microns, so the two are also compared in the objective's own metric"""
OBJECTIVE_REL = 1e-9
PROGRAM_TOLERANCE_M = 2e-3
"""how far the hot path's program (tolerance 1e-6) stops from the exact optimum (docs/slam.md)"""


def steps(windows: list[tuple[Shape, UpdateData]]) -> list[tuple[Shape, UpdateData]]:
    """The windows of Gauss-Newton steps: no cheirality rows."""
    return [(shape, d) for shape, d in windows if not np.any(d.g)]


def compare(windows: list[tuple[Shape, UpdateData]]) -> dict[str, int]:
    """Solve each step both ways where its optimum is unique; assert the same states; count the
    windows, the linear solves and the rows beyond Huber's threshold at the optimum."""
    seen = {"windows": 0, "unique": 0, "more_solves": 0, "huber_linear": 0}
    programs: dict[Shape, WindowProgram] = {}
    for shape, d in windows:
        seen["windows"] += 1
        program = programs.setdefault(shape, WindowProgram(shape, max_iter=200, tolerance=TOLERANCE))
        x_program, _ = program.solve(d)
        if not unique(hessian(shape, d, x_program)):
            continue
        seen["unique"] += 1
        solved = DirectStep(shape).solve(d)
        assert solved is not None, shape
        x, solves = solved
        dx = x - x_program
        assert np.max(np.abs(dx)) <= STATES_M, (shape, np.max(np.abs(dx)))
        metric = 0.5 * dx @ hessian(shape, d, x_program) @ dx
        assert metric <= OBJECTIVE_REL * max(1.0, abs(program.objective)), (shape, metric)
        seen["more_solves"] += solves > 1
        seen["huber_linear"] += bool(np.any(np.abs(rows_at(shape, d.a) @ x + d.offset) > d.huber_m))
    return seen


def test_with_outlier_bearings_the_step_is_the_programs_optimum():
    seen = compare(steps(outlier_windows()))
    assert seen["unique"] >= 0.8 * seen["windows"] > 0, seen
    assert seen["huber_linear"] > 0 and seen["more_solves"] > 0, seen  # the zones were settled


@pytest.mark.slow
def test_on_the_pipelines_windows_the_step_is_the_programs_optimum(lap_runs):
    seen = compare(steps(lap_windows(lap_runs["with"]))[::EVERY])
    assert seen["windows"] >= 100 and seen["unique"] >= 0.8 * seen["windows"], seen


def test_a_state_nothing_holds_leaves_the_step_to_the_program():
    """Two epochs held by a prior and an odometry edge, and a tag with neither a prior nor a bearing:
    the Hessian is singular along the tag."""
    shape = Shape(epochs=2, slots=1, tags=1)
    prior = np.zeros((4 + 2, 4 + 2))
    prior[:4, :4] = np.eye(4)
    blank = UpdateData(
        prior_info=prior,
        velocity_info=np.zeros((2, 2, 2)),
        c=np.zeros(shape.states),
        edge_l=edge_matrix(np.array([0.1])),
        edge_chol=0.01 * np.eye(4)[None],
        edge_delta=np.zeros((1, 4)),
        edge_bias=np.zeros((1, 4, 0)),
        a=np.zeros((shape.rows, 4)),
        offset=np.zeros(shape.rows),
        g=np.zeros((shape.rows, 4)),
        huber_m=1.0,
        hinge=np.zeros(shape.rows),
    )
    assert DirectStep(shape).solve(blank) is None


def test_the_window_takes_its_steps_from_the_direct_solve_and_from_the_program_when_it_declines(monkeypatch):
    """The same scene estimated twice: with the direct solve taking the Gauss-Newton steps, and with
    it declining every one (the program takes them): the robot and the tags agree within what the
    program's tolerance allows (1e-6: within about 2 mm of the exact optimum, docs/slam.md; this
    scene's largest difference is 0.9 mm, on a tag)."""
    sc = scene(seconds=8.0)
    measured = angles(sc, noise_deg=2.0, outliers=0.1, seed=5)
    settings = WindowSettings(window=20, **INDEPENDENT_BURSTS)
    solve, taken = DirectStep.solve, []

    def counted(self: DirectStep, d: UpdateData) -> tuple[np.ndarray, int] | None:
        out = solve(self, d)
        taken.append(out is not None)
        return out

    monkeypatch.setattr(DirectStep, "solve", counted)
    direct, path = estimate(sc, settings, measured, 2.0)
    assert len(taken) > 50 and all(taken)
    monkeypatch.setattr(DirectStep, "solve", lambda self, d: None)
    program, program_path = estimate(sc, settings, measured, 2.0)
    assert np.max(np.abs(path - program_path)) < PROGRAM_TOLERANCE_M
    np.testing.assert_allclose(direct.tag_positions(), program.tag_positions(), atol=PROGRAM_TOLERANCE_M)
