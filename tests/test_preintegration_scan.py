"""The preintegration's recurrences done an interval at a time equal them done sample by sample."""

from __future__ import annotations

import numpy as np
import pytest

from rover.geometry import exp_so3_batch
from rover.operators.preintegration.scan import prefix_products, propagated


@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 40, 41, 129])
def test_prefix_products_equal_the_loop(n):
    rng = np.random.default_rng(n)
    start = exp_so3_batch(rng.normal(size=(1, 3)))[0]
    steps = exp_so3_batch(rng.normal(0, 0.1, (n, 3)))
    before, after = prefix_products(start, steps)
    current = start
    for k in range(n):
        assert np.allclose(before[k], current, atol=1e-13)
        current = current @ steps[k]
    assert np.allclose(after, current, atol=1e-13)
    assert before.shape == (n, 3, 3)


@pytest.mark.parametrize("n", [0, 1, 2, 5, 40, 63, 64, 65])
def test_propagated_equals_the_loop(n):
    rng = np.random.default_rng(100 + n)
    d = 9
    a = np.eye(d)[None] + rng.normal(0, 0.05, (n, d, d))
    root = rng.normal(0, 1e-3, (n, d, d))
    noise = root @ root.transpose(0, 2, 1)
    start = np.diag(rng.uniform(1e-6, 1e-4, d))
    cov = start
    for k in range(n):
        cov = a[k] @ cov @ a[k].T + noise[k]
    assert np.allclose(propagated(start, a, noise), cov, rtol=1e-10, atol=1e-18)
