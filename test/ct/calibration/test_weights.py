"""LLE embedding weights (L2, published NCC, exact NCC) and their MAP variant under the robots' prior."""

import numpy as np
import pytest
from scipy.optimize import minimize

from robot_ct_ros.ct.calibration.lle.weights import (WEIGHTINGS, effective_pixel_fraction, lle_weights,
                                                     posterior_cost)
from robot_ct_ros.ct.metrics import ncc


def _random_problem(rng, n=4, K=6, P=400):
    Y = rng.normal(size=(n, K, P)).cumsum(axis=2)  # smooth-ish, correlated "projections"
    w_true = rng.dirichlet(np.ones(K), size=n)  # sums to 1
    return Y, w_true


@pytest.mark.parametrize("method", WEIGHTINGS)
def test_weights_sum_to_one(method):
    rng = np.random.default_rng(0)
    Y, _ = _random_problem(rng)
    b = Y.mean(axis=1) + rng.normal(scale=0.1, size=(Y.shape[0], Y.shape[2]))
    w = lle_weights(b, Y, method)
    assert w.shape == Y.shape[:2]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-12)


def test_ncc_exact_equals_brute_force_maximiser():
    rng = np.random.default_rng(1)
    K, P = 5, 300
    for trial in range(3):
        # as in LLE: b lies near the neighbours, which are noisy versions of one another
        base = rng.normal(size=P).cumsum()
        Y = base + rng.normal(size=(K, P)) * 3.0
        b = 0.7 * base + rng.normal(size=P) * 3.0 + 4.0
        w = lle_weights(b[None], Y[None], "ncc-exact", reg=0.0)[0]
        Yc = Y - Y.mean(axis=1, keepdims=True)
        assert np.linalg.solve(Yc @ Yc.T, Yc @ (b - b.mean())).sum() > 0  # a finite maximiser exists

        def neg_ncc(free):
            ww = np.append(free, 1.0 - free.sum())
            return -ncc(ww @ Y, b)[0]

        best = None
        for start in range(4):
            x0 = rng.dirichlet(np.ones(K))[:-1]
            res = minimize(neg_ncc, x0, method="BFGS", options={"gtol": 1e-12, "maxiter": 10000})
            best = res if best is None or res.fun < best.fun else best
        w_brute = np.append(best.x, 1.0 - best.x.sum())
        assert ncc(w @ Y, b)[0] >= -best.fun - 1e-10
        np.testing.assert_allclose(w, w_brute, atol=1e-4)


def test_exact_embedding_recovered_and_ncc_ignores_gain_and_offset():
    rng = np.random.default_rng(2)
    Y, w_true = _random_problem(rng, n=3, K=4, P=500)
    b = np.einsum("nk,nkp->np", w_true, Y)
    for method in ("l2", "ncc-exact"):
        np.testing.assert_allclose(lle_weights(b, Y, method, reg=0.0), w_true, atol=1e-8)
    b_gain_offset = 2.5 * b + 7.0  # what truncation and calibration drifts do to a projection
    np.testing.assert_allclose(lle_weights(b_gain_offset, Y, "ncc-exact", reg=0.0), w_true, atol=1e-8)
    assert np.abs(lle_weights(b_gain_offset, Y, "l2", reg=0.0) - w_true).max() > 1e-2


def test_masked_and_nan_pixels_are_ignored():
    rng = np.random.default_rng(3)
    Y, w_true = _random_problem(rng, n=2, K=4, P=300)
    b = np.einsum("nk,nkp->np", w_true, Y)
    b_bad = b.copy()
    b_bad[:, :20] = np.nan          # dead pixels
    b_bad[:, 20:40] = 1e6           # hot pixels, masked out
    mask = np.ones(b.shape[1], bool)
    mask[20:40] = False
    for method in WEIGHTINGS:
        w = lle_weights(b_bad, Y, method, mask=mask, reg=0.0)
        assert np.all(np.isfinite(w))
        if method != "ncc":  # the published closed form is not exact for correlated neighbours
            np.testing.assert_allclose(w, w_true, atol=1e-8)


def test_rejects_bad_shapes_and_methods():
    with pytest.raises(ValueError):
        lle_weights(np.zeros((2, 10)), np.zeros((2, 3, 11)))
    with pytest.raises(ValueError):
        lle_weights(np.zeros((1, 10)), np.zeros((1, 3, 10)), method="l1")


def test_ncc_exact_falls_back_to_best_neighbour_when_no_finite_maximiser():
    rng = np.random.default_rng(5)
    for _ in range(50):  # find random data whose NCC maximiser lies on the wrong side of sum(w) = 1
        Y = rng.normal(size=(1, 4, 100))
        b = rng.normal(size=(1, 100))
        Yc = Y[0] - Y[0].mean(axis=1, keepdims=True)
        if np.linalg.solve(Yc @ Yc.T, Yc @ (b[0] - b[0].mean())).sum() < 0:
            break
    w = lle_weights(b, Y, "ncc-exact", reg=0.0)[0]
    assert np.count_nonzero(w) == 1 and w.sum() == 1.0
    assert np.argmax(w) == np.argmax(ncc(Y[0], np.repeat(b, 4, axis=0)))


def _constrained_minimum(objective, K, rng):
    best = None
    for _ in range(4):
        x0 = rng.dirichlet(np.ones(K))[:-1]
        res = minimize(lambda free: objective(np.append(free, 1.0 - free.sum())), x0, method="BFGS",
                       options={"gtol": 1e-10, "maxiter": 10000})
        best = res if best is None or res.fun < best.fun else best
    return np.append(best.x, 1.0 - best.x.sum())


@pytest.mark.parametrize("method", ["l2", "ncc-exact"])
def test_map_weights_equal_the_brute_force_posterior_minimiser(method):
    """Data term in units of the best data-only fit's residual variance, plus a Gaussian prior on
    the embedded parameters (for ncc-exact at the unconstrained fit's gain)."""
    rng = np.random.default_rng(7)
    K, P, D = 5, 300, 9
    base = rng.normal(size=P).cumsum()
    Y = base + rng.normal(size=(K, P)) * 3.0
    b = 0.8 * base + rng.normal(size=P) * 3.0 + (4.0 if method == "ncc-exact" else 0.0)
    g = rng.normal(size=(K, D))
    inv_var = rng.uniform(0.5, 2.0, size=D) * 30.0
    w = lle_weights(b[None], Y[None], method, reg=0.0, prior=(g[None], inv_var))[0]
    np.testing.assert_allclose(w.sum(), 1.0, atol=1e-12)
    if method == "l2":
        w0 = lle_weights(b[None], Y[None], "l2", reg=0.0)[0]
        var = np.sum((b - w0 @ Y) ** 2) / P
        gain, bt, Yt = 1.0, b, Y
    else:
        bt, Yt = b - b.mean(), Y - Y.mean(axis=1, keepdims=True)
        v = np.linalg.solve(Yt @ Yt.T, Yt @ bt)
        gain, var = v.sum(), np.sum((bt - v @ Yt) ** 2) / P

    def posterior(ww):
        return np.sum((bt - gain * (ww @ Yt)) ** 2) / var + (ww @ g) ** 2 @ inv_var

    w_brute = _constrained_minimum(posterior, K, rng)
    assert posterior(w) <= posterior(w_brute) + 1e-8
    np.testing.assert_allclose(w, w_brute, atol=1e-4)
    # a vanishing prior gives the data-only weights back; a strong one pulls the parameters in
    w_data = lle_weights(b[None], Y[None], method, reg=0.0)[0]
    np.testing.assert_allclose(lle_weights(b[None], Y[None], method, reg=0.0, prior=(g[None], inv_var * 1e-12))[0],
                               w_data, atol=1e-8)
    strong = lle_weights(b[None], Y[None], method, reg=0.0, prior=(g[None], inv_var * 1e6))[0]
    M = (g * inv_var) @ g.T  # the affine combination with the smallest prior term
    w_min = np.linalg.solve(M, np.ones(K)) / np.linalg.solve(M, np.ones(K)).sum()
    np.testing.assert_allclose(strong, w_min, atol=1e-3)


def test_effective_pixel_fraction_counts_white_residuals_fully_and_structured_ones_little():
    """White residuals count fully; residuals at the edges' scale hardly; a smooth bowl (what
    FDK of a truncated scan leaves) is mostly taken out by the high-pass before it counts."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(3)
    n, R, C = 3, 48, 160
    pred = rng.normal(size=(n, R, C)).cumsum(axis=2)
    mask = np.ones((n, R, C), bool)
    mask[:, :, 5] = False  # a chip gap
    fit = 2.0 * pred + 1.0  # gain and offset are not residual
    white = fit + rng.normal(size=(n, R, C))
    edges = fit + gaussian_filter(rng.normal(size=(n, R, C)) * 5.0, (0, 1.5, 1.5)) + 0.05 * rng.normal(size=(n, R, C))
    bowl = fit + 20.0 * np.linspace(-1, 1, C)[None, None, :] ** 2 + rng.normal(size=(n, R, C))
    assert np.all(effective_pixel_fraction(white, pred, mask) > 0.8)
    assert np.all(effective_pixel_fraction(edges, pred, mask) < 0.02)
    high_passed, raw = effective_pixel_fraction(bowl, pred, mask), effective_pixel_fraction(bowl, pred, mask, highpass_px=0)
    assert np.all(high_passed > 0.05) and np.all(high_passed > 100 * raw), (high_passed, raw)


def test_posterior_cost_is_chi_square_plus_prior():
    d = np.array([[0.1, 0.2, np.inf]])
    params = np.zeros((1, 3, 2))
    params[0, 1] = [1.0, 0.0]
    cost = posterior_cost(d, params, np.full((1, 3), 100.0), "l2", np.array([4.0, 1.0]))
    np.testing.assert_allclose(cost[0, :2], [100.0, 200.0 + 4.0])
    assert cost[0, 2] == np.inf
    rho = 1.0 - d[0, :2]
    ncc_cost = posterior_cost(d, params, np.full((1, 3), 100.0), "ncc", np.array([4.0, 1.0]))
    np.testing.assert_allclose(ncc_cost[0, 1], 100.0 * (1 - rho[1] ** 2) / (1 - rho[0] ** 2) + 4.0)
