"""The sliding-window program written in CVXPY: the executable specification of `window_program`.

`WindowProgram` hand-compiles the program of one update into Clarabel's matrices for speed; this
module states the same program as the math reads (docs/slam.md), with CVXPY Parameters so it is
built once per window shape and re-solved (DPP: every parameter enters affinely, so CVXPY
canonicalizes once and only re-fills the numbers). It is solved with Clarabel through CVXPY.
tests/test_window_model.py solves windows captured from real runs both ways and fails on any
difference; `slam`'s `batch: true` solves with this model.

    min   1/2 |R (x_P - 0)|^2 - c'x                      prior (H = R'R over the prior's states)
        + 1/2 sum_k y_k' W_k y_k                         wheel speed information per epoch,
                                                         y_k = v_k (and the wheel scale s)
        + 1/2 |rho|^2                                    whitened odometry residuals
        + sum_i ( 1/2 n_i^2 + M t_i ) + sum_i w_i h_i    Huber split, cheirality hinge
    s.t.  v_k+1 - v_k + J_e,v b - C_e,v rho_e = dv_e     each odometry edge e = (k, k+1),
          p_k+1 - p_k - dt_e v_k + J_e,p b - C_e,p rho_e = dp_e
                                                         C_e the Cholesky factor of its covariance,
                                                         J_e how it moves with the bias states b
          |a_i'x + k_i - n_i| <= t_i                     each AoA slot i
          h_i >= 0,  h_i >= -g_i'x

where 1/2 n^2 + M |r - n| minimized over n is 1/2 huber_M(r).
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from rover.operators.slam.layout import Shape, prior_indices, slot_columns, velocity_columns
from rover.operators.slam.window_program import SolverFailed, UpdateData, edge_matrix

TOLERANCE = 1e-9
"""Clarabel's gap and feasibility tolerances here: a specification is solved tighter than the hot path"""
MAX_ITER = 200


def _square_root(info: np.ndarray) -> np.ndarray:
    """R with R'R = info for a symmetric positive semidefinite matrix (negative rounding clipped)."""
    values, vectors = np.linalg.eigh(0.5 * (info + info.T))
    return np.sqrt(np.clip(values, 0.0, None))[:, None] * vectors.T


class WindowModel:
    """The window's program for one shape, in CVXPY; `solve` takes the numbers of one update, as
    `WindowProgram.solve` does, and returns the states and Clarabel's iteration count."""

    def __init__(self, shape: Shape, max_iter: int = MAX_ITER, tolerance: float = TOLERANCE):
        self.shape = shape
        self.max_iter, self.tolerance = max_iter, tolerance
        e, r = shape.epochs, shape.rows
        edges = max(e - 1, 0)
        self.prior_index = prior_indices(shape)
        self.columns = slot_columns(shape)
        width = self.columns.shape[1]

        self.x = x = cp.Variable(shape.states, name="x")
        self.rho = rho = cp.Variable((max(edges, 1), 4), name="rho")  # one unused row in a one-epoch window
        n, t, h = cp.Variable(r, name="n"), cp.Variable(r, name="t"), cp.Variable(r, name="h")

        self.prior_root = cp.Parameter((len(self.prior_index), len(self.prior_index)), name="R")
        self.c = cp.Parameter(shape.states, name="c")
        self.wheel_columns = velocity_columns(shape)
        w = self.wheel_columns.shape[1]
        self.wheel_root = [[cp.Parameter(e, name=f"S_{i}{j}") for j in range(w)] for i in range(w)]
        """the entries of each epoch's W_k = S_k'S_k over y_k (its velocity, and the wheel scale)"""
        self.dt = cp.Parameter(max(edges, 1), name="dt")
        self.chol = [[cp.Parameter(max(edges, 1), name=f"C_{i}{j}") for j in range(4)] for i in range(4)]
        self.delta = cp.Parameter((max(edges, 1), 4), name="delta")
        self.bias_jacobian = [
            [cp.Parameter(max(edges, 1), name=f"J_{i}{j}") for j in range(shape.biases)] for i in range(4)
        ]
        bias = [x[int(j)] for j in shape.bias_index]
        self.a = [cp.Parameter(r, name=f"a_{j}") for j in range(width)]
        self.g = [cp.Parameter(r, name=f"g_{j}") for j in range(width)]
        self.k = cp.Parameter(r, name="k")
        self.m = cp.Parameter(nonneg=True, name="M")
        self.hinge = cp.Parameter(r, nonneg=True, name="w")

        position = [x[4 * np.arange(e) + i] for i in range(2)]
        velocity = [x[4 * np.arange(e) + 2 + i] for i in range(2)]
        # the square roots' images as variables: parameters then enter constraints only, and the
        # objective's quadratic part is parameter-free (what CVXPY's QP path needs to stay DPP)
        prior = cp.Variable(len(self.prior_index), name="R x_P")
        wheel = cp.Variable((e, w), name="S_k y_k")
        wheel_states = [x[self.wheel_columns[:, j]] for j in range(w)]
        objective = (
            0.5 * cp.sum_squares(prior)
            - self.c @ x
            + 0.5 * cp.sum_squares(wheel)
            + 0.5 * cp.sum_squares(rho)
            + 0.5 * cp.sum_squares(n)
            + self.m * cp.sum(t)
            + self.hinge @ h
        )
        constraints = [
            prior == self.prior_root @ x[self.prior_index],
            *([] if edges else [rho == 0]),
            *(
                wheel[:, i] == sum(cp.multiply(self.wheel_root[i][j], wheel_states[j]) for j in range(w))
                for i in range(w)
            ),
            h >= 0,
        ]
        if edges:
            before, after = np.arange(edges), np.arange(1, e)
            whitened = [sum(cp.multiply(self.chol[i][j], rho[:, j]) for j in range(4)) for i in range(4)]
            drift = [
                sum((cp.multiply(jb, b) for jb, b in zip(self.bias_jacobian[i], bias, strict=True)), 0)
                for i in range(4)
            ]
            for i in range(2):  # [dv, dp] per axis, as the edge's residual orders them
                constraints.append(
                    velocity[i][after] - velocity[i][before] + drift[i] - whitened[i] == self.delta[:, i]
                )
                constraints.append(
                    position[i][after]
                    - position[i][before]
                    - cp.multiply(self.dt, velocity[i][before])
                    + drift[2 + i]
                    - whitened[2 + i]
                    == self.delta[:, 2 + i]
                )
        row = sum(cp.multiply(self.a[j], x[self.columns[:, j]]) for j in range(width)) + self.k
        toward = sum(cp.multiply(self.g[j], x[self.columns[:, j]]) for j in range(width))
        constraints += [cp.abs(row - n) <= t, h >= -toward]
        self.problem = cp.Problem(cp.Minimize(objective), constraints)
        assert self.problem.is_dpp(), "the window model must stay DPP: built once, re-solved"

    def set(self, d: UpdateData) -> None:
        """Fill the parameters with the numbers of one update."""
        e = self.shape.epochs
        self.prior_root.value = _square_root(d.prior_info)
        self.c.value = d.c
        w = self.wheel_columns.shape[1]
        roots = np.array([_square_root(info) for info in d.velocity_info]) if e else np.zeros((0, w, w))
        for i, row in enumerate(self.wheel_root):
            for j, root in enumerate(row):
                root.value = roots[:, i, j]
        if len(d.edge_l):
            dt = -d.edge_l[:, 2, 2]
            if not np.array_equal(d.edge_l, edge_matrix(dt)):
                raise ValueError("window model: an odometry edge's L is not the constant-velocity model's")
            self.dt.value = dt
            for i in range(4):
                for j in range(4):
                    self.chol[i][j].value = d.edge_chol[:, i, j]
            self.delta.value = d.edge_delta
            for i, row in enumerate(self.bias_jacobian):
                for j, jb in enumerate(row):
                    jb.value = d.edge_bias[:, i, j]
        else:
            self.dt.value = np.zeros(1)
            for i in range(4):
                for j in range(4):
                    self.chol[i][j].value = np.zeros(1)
            self.delta.value = np.zeros((1, 4))
            for row in self.bias_jacobian:
                for jb in row:
                    jb.value = np.zeros(1)
        for j in range(len(self.a)):
            self.a[j].value = d.a[:, j]
            self.g[j].value = d.g[:, j]
        self.k.value = d.offset
        self.m.value = d.huber_m
        self.hinge.value = d.hinge

    def solve(self, d: UpdateData) -> tuple[np.ndarray, int]:
        """Minimize for one update: the states x and Clarabel's iteration count."""
        self.set(d)
        tol = self.tolerance
        self.problem.solve(solver=cp.CLARABEL, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol, max_iter=self.max_iter)
        if self.problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            raise SolverFailed(f"slam: Clarabel (through CVXPY) stopped with status {self.problem.status}")
        stats = self.problem.solver_stats
        return np.asarray(self.x.value, dtype=float), int(stats.num_iters or 0)

    @property
    def objective(self) -> float:
        """The optimal value of the last solve."""
        return float(self.problem.value)
