"""The convex sliding-window SLAM: the operator, the estimator and its conic program."""
