"""The LLE estimator: weights, sampling, the per-view pass."""
