"""A Gauss-Newton step of the window solved directly: the window program (window_program.py) without
its cheirality rows is an unconstrained, smooth, strongly convex problem in the states x,

    F(x) = 0.5 x'Hx - c'x + 0.5 sum_e |C_e^-1 (G_e x - y_e)|^2 + sum_i 0.5 huber_M(a_i'x + k_i)

(G_e = [L_e J_e], the odometry rows whitened by their covariance's Cholesky factor C_e), and
piecewise quadratic: each AoA row is quadratic within M and linear beyond. Newton's method finds
its minimum: the gradient (the same on both sides of M), the curvature of Huber's majorizer (weight
M/|r| on the rows beyond M, whose minimum never raises F) until the rows' zones hold from one point
to the next, then the Hessian of those zones, each step halved until F does not grow (with rows
far beyond M the zones can otherwise cycle), until a whole Newton step lands in the zones it was
taken in: that point is the exact optimum, usually after one solve, as the windows rarely reach
Huber's linear zone. Clarabel's interior point takes five or
more factorizations of a system three times larger for the same point (within its tolerance). A
Hessian that is not positive definite, or zones that do not settle within MAX_PASSES, leave the
step to the program.

The odometry's information reaches 1e12 over one epoch (docs/slam.md), so the gradient is always
computed in the whitened square-root form, where nothing is squared, and the last step is refined
with the same factor (REFINEMENTS times; each divides the error by about the condition number
times the rounding unit, 1e-4)."""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from rover.operators.slam.layout import EPOCH_STATES, Shape, prior_indices, slot_columns, velocity_columns
from rover.operators.slam.window_program import UpdateData

MAX_PASSES = 20
"""Newton steps before the step is left to the program"""
MAX_HALVINGS = 30
"""halvings of one step before the step is left to the program"""
VALUE_REL = 1e-12
"""a step is taken when F grows by no more than this (its rounding at the optimum)"""
REFINEMENTS = 1
"""corrections of each solve from its gradient in square-root form"""
DIRECT_MAX_STATES = 300
"""windows with more states are left to the program, whose sparse factorization then costs less than
the dense one (`paper`, one core: 1.3 against 0.5 ms at 129 states, the 30-epoch window; 2.2 against
1.8 at 251; 3.9 against 5.0 at 413)"""


class DirectStep:
    """The Gauss-Newton step's solve for one window shape (index maps built once per shape)."""

    def __init__(self, shape: Shape):
        self.shape = shape
        n = shape.states
        edges = max(shape.epochs - 1, 0)
        pairs = EPOCH_STATES * np.arange(edges)[:, None] + np.arange(2 * EPOCH_STATES)
        self.spans = np.concatenate([pairs, np.broadcast_to(shape.bias_index, (edges, shape.biases))], axis=1)
        self.columns = slot_columns(shape)
        self.slot_rows = np.broadcast_to(np.arange(shape.rows)[:, None], self.columns.shape)
        prior, velocity = prior_indices(shape)[None], velocity_columns(shape)
        self.smooth_flat = np.concatenate([(b[:, :, None] * n + b[:, None, :]).ravel() for b in (prior, velocity)])
        self.edge_flat = (self.spans[:, :, None] * n + self.spans[:, None, :]).ravel()

    def solve(self, d: UpdateData) -> tuple[np.ndarray, int] | None:
        """The step's exact minimizer and the Newton steps it took; None when the Hessian is not
        positive definite or the Huber zones did not settle (the caller solves the program)."""
        n = self.shape.states
        # the prior and wheel terms (H), and the odometry rows whitened: C^-1 [L J], C^-1 y
        smooth = np.bincount(
            self.smooth_flat, weights=np.concatenate([d.prior_info.ravel(), d.velocity_info.ravel()]), minlength=n * n
        ).reshape(n, n)
        whitened = np.linalg.solve(
            d.edge_chol, np.concatenate([d.edge_l, d.edge_bias, d.edge_delta[:, :, None]], axis=2)
        )
        problem = _Problem(self, d, smooth, whitened[:, :, :-1], whitened[:, :, -1])
        edges = np.einsum("eki,ekj->eij", problem.white, problem.white).ravel()
        fixed = smooth + np.bincount(self.edge_flat, weights=edges, minlength=n * n).reshape(n, n)
        x = np.zeros(n)
        value, gradient, r = problem.at(x)
        zones = None
        for passes in range(1, MAX_PASSES + 1):
            beyond = np.abs(r) > d.huber_m
            # Newton once the zones hold from one point to the next; before, the majorizer's curvature
            newton = not beyond.any() or (zones is not None and np.array_equal(beyond, zones))
            weight = np.where(beyond, 0.0 if newton else d.huber_m / np.maximum(np.abs(r), d.huber_m), 1.0)
            weighted = problem.rows * np.sqrt(weight)[:, None]
            factor, info = dpotrf(fixed + weighted.T @ weighted, lower=0, clean=0, overwrite_a=1)
            if info != 0:
                return None
            step = dpotrs(factor, gradient, lower=0)[0]
            for halving in range(MAX_HALVINGS + 1):
                trial = x - 0.5**halving * step
                trial_value, trial_gradient, trial_r = problem.at(trial)
                if trial_value <= value + VALUE_REL * abs(value):
                    break
            else:
                return None
            settled = newton and halving == 0 and np.array_equal(np.abs(trial_r) > d.huber_m, beyond)
            x, value, gradient, r, zones = trial, trial_value, trial_gradient, trial_r, beyond
            if settled:
                for refinement in range(REFINEMENTS):  # the first from the gradient the step already has
                    gradient = problem.at(x)[1] if refinement else gradient
                    x = x - dpotrs(factor, gradient, lower=0)[0]
                return x, passes
        return None


class _Problem:
    """F, its gradient and the AoA rows' residuals at a point, the odometry in square-root form."""

    def __init__(self, step: DirectStep, d: UpdateData, smooth: np.ndarray, white: np.ndarray, target: np.ndarray):
        self.d, self.smooth, self.white, self.target = d, smooth, white, target
        self.spans = step.spans
        self.rows = np.zeros((step.shape.rows, step.shape.states))
        self.rows[step.slot_rows, step.columns] = d.a

    def at(self, x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """F at x, its gradient, and the AoA rows' residuals."""
        d = self.d
        m = d.huber_m
        r = self.rows @ x + d.offset
        beyond = np.abs(r) > m
        misfit = np.einsum("eki,ei->ek", self.white, x[self.spans]) - self.target
        hx = self.smooth @ x
        huber = np.where(beyond, 2 * m * np.abs(r) - m * m, r * r)
        value = 0.5 * float(x @ hx) - float(d.c @ x) + 0.5 * float(np.sum(misfit**2)) + 0.5 * float(np.sum(huber))
        gradient = hx - d.c + self.rows.T @ np.clip(r, -m, m)
        gradient += np.bincount(
            self.spans.ravel(), weights=np.einsum("eki,ek->ei", self.white, misfit).ravel(), minlength=len(x)
        )
        return value, gradient, r
