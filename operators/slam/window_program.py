"""The convex program of one sliding-window update, built once per shape and re-solved with Clarabel.

Variables z = [x, rho, n, t, h]: x the window's states (per epoch position and velocity in x/y,
then the tags' positions, then the states b shared by the window: the accelerometer biases and,
with wheel odometry, the wheel scale); rho the whitened odometry residuals; per AoA slot a Huber
split (n, t) and a cheirality slack h. The program is

    min  0.5 x'Hx - c'x + 0.5 |rho|^2 + sum_i 0.5 huber_M(a_i'x + k_i) + sum_i hinge_i h_i
    s.t. L_e x + J_e b - C_e rho_e = y_e   (each odometry edge; C_e the Cholesky factor of its covariance,
                                            J_e how its deltas move with the bias)
         h_i >= max(0, -g_i'x)

with (H, c) the prior and the wheel terms (each epoch's over velocity_columns), and
huber_M(r) = min_n n^2 + 2M|r - n| written with |r - n| <= t, so the program stays a conic QP.
The odometry enters in square-root form because the IMU is extremely precise over one epoch
(information up to 1e12): squared into P it breaks the interior-point method's accuracy, as
constraint rows it does not.

The sparsity is a function of the window's shape only (epochs, slots per epoch, tags): a slot
without a bearing has zero coefficients, so one factorization pattern serves every update.
The same program does the Gauss-Newton steps on the angle residual: then a_i is the linearized
atan2 row and k_i its offset.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import clarabel
import numpy as np
import scipy.sparse as sp

from rover.errors import RoverError
from rover.operators.slam.layout import Shape, prior_indices, slot_columns, velocity_columns


class SolverFailed(RoverError):
    """Clarabel did not reach a solution (reported, the update keeps its previous estimate)."""


class FixedPattern:
    """A sparse matrix whose nonzero positions never change: COO entries in a fixed order
    (duplicates summed) map to CSC data with one bincount."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]):
        self.shape = shape
        key = cols.astype(np.int64) * shape[0] + rows
        unique, self.inverse = np.unique(key, return_inverse=True)
        self.indices = (unique % shape[0]).astype(np.int64)
        counts = np.bincount(unique // shape[0], minlength=shape[1])
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.nnz = len(unique)

    def data(self, values: np.ndarray) -> np.ndarray:
        return np.bincount(self.inverse, weights=values, minlength=self.nnz)

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """The matrix of CSC `data` (as `data` returns it)."""
        return sp.csc_matrix((data, self.indices, self.indptr), shape=self.shape)


L_PATTERN = (np.array([0, 0, 1, 1, 2, 2, 2, 3, 3, 3]), np.array([2, 6, 3, 7, 0, 2, 4, 1, 3, 5]))
"""Nonzeros of an edge's L (4x8) over [p_k, v_k, p_k+1, v_k+1] -> [r_v, r_p]."""


def edge_matrix(dt: np.ndarray) -> np.ndarray:
    """L for each edge: r_v = v_k+1 - v_k - dv, r_p = p_k+1 - p_k - v_k dt - dp."""
    n = len(dt)
    eye = np.eye(2)
    lmat = np.zeros((n, 4, 8))
    lmat[:, 0:2, 2:4], lmat[:, 0:2, 6:8] = -eye, eye
    lmat[:, 2:4, 0:2], lmat[:, 2:4, 4:6] = -eye, eye
    lmat[:, 2:4, 2:4] = -dt[:, None, None] * eye
    return lmat


@dataclass(frozen=True)
class UpdateData:
    """The numbers of one solve."""

    prior_info: np.ndarray
    """H over prior_indices"""
    velocity_info: np.ndarray
    """(epochs, w, w) information on each epoch's velocity_columns (wheel odometry, the no-sideways
    and turn-in-place terms; zero without)"""
    c: np.ndarray
    """linear term over all states"""
    edge_l: np.ndarray
    """(edges, 4, 8)"""
    edge_chol: np.ndarray
    """(edges, 4, 4) Cholesky factors of the odometry covariances"""
    edge_delta: np.ndarray
    """(edges, 4) [dv, dp]"""
    edge_bias: np.ndarray
    """(edges, 4, biases) each edge residual's coefficients on the bias states"""
    a: np.ndarray
    """(rows, columns) Huber row coefficients at slot_columns"""
    offset: np.ndarray
    """(rows,) constant of each Huber row"""
    g: np.ndarray
    """(rows, columns) cheirality coefficients"""
    huber_m: float
    hinge: np.ndarray
    """(rows,) hinge weight per slot"""


class Program(Protocol):
    """What the sliding window needs of a program: this module's compiled one or the CVXPY model."""

    shape: Shape

    def solve(self, d: UpdateData) -> tuple[np.ndarray, int]: ...


class WindowProgram:
    """The conic program for one window shape; `solve` takes the numbers of one update."""

    def __init__(self, shape: Shape, max_iter: int = 50, tolerance: float = 1e-6):
        self.shape = shape
        nx, r, ne = shape.states, shape.rows, max(shape.epochs - 1, 0)
        self.rho0 = nx
        self.n0 = nx + 4 * ne
        self.t0, self.h0 = self.n0 + r, self.n0 + 2 * r
        self.nz = self.n0 + 3 * r
        pri = prior_indices(shape)
        upper = pri[:, None] <= pri[None, :]
        self.prior_upper = upper.ravel()
        vel = velocity_columns(shape)
        self.vel_upper = np.triu_indices(vel.shape[1])
        vel_rows = vel[:, self.vel_upper[0]].ravel()
        vel_cols = vel[:, self.vel_upper[1]].ravel()
        p_rows = np.concatenate(
            [
                np.repeat(pri, len(pri))[self.prior_upper],
                vel_rows,
                self.rho0 + np.arange(4 * ne),
                self.n0 + np.arange(r),
            ]
        )
        p_cols = np.concatenate(
            [np.tile(pri, len(pri))[self.prior_upper], vel_cols, self.rho0 + np.arange(4 * ne), self.n0 + np.arange(r)]
        )
        self.p_pattern = FixedPattern(p_rows, p_cols, (self.nz, self.nz))
        self.p_tail = np.ones(4 * ne + r)
        edge = np.arange(ne)
        li, lj = L_PATTERN
        self.l_index = (li, lj)
        nb = shape.biases
        odo_rows = np.concatenate(
            [
                (4 * edge[:, None] + li).ravel(),
                np.repeat(4 * edge[:, None] + np.arange(4), 4, axis=1).ravel(),
                np.repeat(4 * edge[:, None] + np.arange(4), nb, axis=1).ravel(),
            ]
        )
        odo_cols = np.concatenate(
            [
                (4 * edge[:, None] + lj).ravel(),
                (self.rho0 + 4 * edge[:, None] + np.tile(np.arange(4), 4)).ravel(),
                np.tile(shape.bias_index, 4 * ne),
            ]
        )
        self.columns = slot_columns(shape)
        width = self.columns.shape[1]
        slot = np.arange(r)
        base = 4 * ne + 4 * slot
        # slot rows: +-(a_i'x + k_i - n_i) - t_i <= 0, -h_i <= 0, -g_i'x - h_i <= 0
        a_rows = np.concatenate([np.repeat(base, width), np.repeat(base + 1, width), np.repeat(base + 3, width)])
        a_cols = np.tile(self.columns.ravel(), 3)
        aux_rows = np.concatenate([base, base + 1, base, base + 1, base + 2, base + 3])
        aux_cols = np.concatenate(
            [self.n0 + slot, self.n0 + slot, self.t0 + slot, self.t0 + slot, self.h0 + slot, self.h0 + slot]
        )
        self.aux_values = np.concatenate([-np.ones(r), np.ones(r), -np.ones(r), -np.ones(r), -np.ones(r), -np.ones(r)])
        self.a_pattern = FixedPattern(
            np.concatenate([odo_rows, a_rows, aux_rows]),
            np.concatenate([odo_cols, a_cols, aux_cols]),
            (4 * ne + 4 * r, self.nz),
        )
        self.equalities = 4 * ne
        self.cones = ([clarabel.ZeroConeT(4 * ne)] if ne else []) + [clarabel.NonnegativeConeT(4 * r)]
        self.settings = clarabel.DefaultSettings()
        self.settings.verbose = False
        self.settings.max_iter = max_iter
        self.settings.tol_gap_abs = self.settings.tol_gap_rel = self.settings.tol_feas = tolerance
        self.solver: clarabel.DefaultSolver | None = None
        self.objective = float("nan")
        """the optimal value of the last solve (the quadratic and linear terms, no constant)"""

    def solve(self, d: UpdateData) -> tuple[np.ndarray, int]:
        """Minimize for one update; returns the states x and the iteration count."""
        r = self.shape.rows
        velocity = d.velocity_info[:, self.vel_upper[0], self.vel_upper[1]].ravel()
        p = self.p_pattern.data(np.concatenate([d.prior_info.ravel()[self.prior_upper], velocity, self.p_tail]))
        q = np.concatenate([-d.c, np.zeros(self.n0 - self.rho0 + r), np.full(r, d.huber_m), d.hinge])
        li, lj = self.l_index
        l_values = d.edge_l[:, li, lj]
        a_data = self.a_pattern.data(
            np.concatenate(
                [
                    l_values.ravel(),
                    -d.edge_chol.reshape(len(d.edge_chol), 16).ravel(),
                    d.edge_bias.ravel(),
                    d.a.ravel(),
                    -d.a.ravel(),
                    -d.g.ravel(),
                    self.aux_values,
                ]
            )
        )
        b = np.zeros(self.equalities + 4 * r)
        b[: self.equalities] = d.edge_delta.ravel()
        b[self.equalities :: 4] = -d.offset
        b[self.equalities + 1 :: 4] = d.offset
        if self.solver is None:
            self.solver = clarabel.DefaultSolver(
                self.p_pattern.matrix(p), q, self.a_pattern.matrix(a_data), b, self.cones, self.settings
            )
        else:
            self.solver.update(P=p, q=q, A=a_data, b=b)
        solution = self.solver.solve()
        status = str(solution.status)
        if status not in ("Solved", "AlmostSolved"):
            raise SolverFailed(f"slam: Clarabel stopped with status {status}")
        self.objective = float(solution.obj_val)
        return np.asarray(solution.x)[: self.shape.states], int(solution.iterations)
