"""Comparing a run with ground truth: metrics and figures."""
