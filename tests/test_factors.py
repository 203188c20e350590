"""The window's measurement models: the odometry edge over more bias states."""

from __future__ import annotations

import numpy as np

from rover.operators.slam.factors import Edge, bias_jacobian


def test_an_edge_over_more_bias_states_is_the_edge_built_with_their_zero_columns():
    rng = np.random.default_rng(3)
    root = rng.standard_normal((4, 4))
    covariance = root @ root.T + 0.1 * np.eye(4)
    jacobian = bias_jacobian(0.2, 0.5, 0.09)
    edge = Edge(0.09, rng.standard_normal(4), covariance, jacobian)
    padded = edge.with_bias_columns(1)
    built = Edge(0.09, edge.delta, covariance, np.pad(jacobian, ((0, 0), (0, 1))))
    assert padded.bias_jacobian.shape == (4, 5) and padded.block.shape == (13, 13)
    np.testing.assert_array_equal(padded.bias_jacobian, built.bias_jacobian)
    np.testing.assert_allclose(padded.block, built.block, rtol=1e-12, atol=1e-12 * np.abs(built.block).max())
    np.testing.assert_array_equal(padded.chol, built.chol)
    assert edge.bias_jacobian.shape == (4, 4) and edge.block.shape == (12, 12), "the original edge is left as it was"
