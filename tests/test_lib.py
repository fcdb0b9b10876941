"""The small-function layer (ot_filter.lib) against dense and closed-form references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ot_filter.lib import ensemble, fallback, gaussian, static, validation, weights


def _random(shape, seed=0):
    return np.random.default_rng(seed).normal(size=shape)


def test_cholesky_gain_and_log_density_match_dense_formulas():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(4, 4))
    s = a @ a.T + 4 * np.eye(4)
    c = rng.normal(size=(3, 4))
    gain, chol = gaussian.cholesky_gain(jnp.asarray(c), jnp.asarray(s))
    np.testing.assert_allclose(gain, c @ np.linalg.inv(s), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(chol @ chol.T, s, rtol=1e-5, atol=1e-5)
    r = rng.normal(size=4)
    dense = -0.5 * (4 * np.log(2 * np.pi) + np.linalg.slogdet(s)[1] + r @ np.linalg.solve(s, r))
    np.testing.assert_allclose(gaussian.gaussian_log_density(jnp.asarray(r), chol), dense, rtol=1e-5)


def test_masked_statistics_ignore_padding_even_when_it_is_nan():
    x = _random((7, 3))
    active = np.array([True] * 5 + [False] * 2)
    padded = x.copy()
    padded[~active] = np.nan
    mean, anomalies = ensemble.masked_mean_and_anomalies(jnp.asarray(padded), jnp.asarray(active))
    np.testing.assert_allclose(mean, x[:5].mean(0), atol=1e-6)
    np.testing.assert_allclose(anomalies[:5], x[:5] - x[:5].mean(0), rtol=1e-5, atol=1e-6)
    assert np.all(np.asarray(anomalies[5:]) == 0)
    mean, std = ensemble.masked_mean_and_std(jnp.asarray(padded), jnp.asarray(active))
    np.testing.assert_allclose(std, x[:5].std(0), rtol=1e-5)
    # every row active: the unmasked formula
    full_mean, full_anomalies = ensemble.mean_and_anomalies(jnp.asarray(x))
    np.testing.assert_allclose(full_mean, x.mean(0), atol=1e-6)  # float32 sums of O(1) values
    np.testing.assert_allclose(full_anomalies, x - x.mean(0), rtol=1e-5, atol=1e-6)


def test_weighted_covariance_matches_numpy_and_collapses_to_equal_weights():
    x = _random((50, 3), seed=2)
    w = np.random.default_rng(3).uniform(size=50)
    w /= w.sum()
    cov = ensemble.weighted_covariance(jnp.asarray(x), jnp.log(jnp.asarray(w)))
    np.testing.assert_allclose(cov, np.cov(x.T, aweights=w), rtol=1e-4, atol=1e-6)
    collapsed = np.full(50, -np.inf)
    collapsed[0] = 0.0
    np.testing.assert_allclose(
        ensemble.weighted_covariance(jnp.asarray(x), jnp.asarray(collapsed)), np.cov(x.T), rtol=1e-4
    )
    # The variances alone (O(N n), what the filters' spread uses): the covariance's diagonal,
    # with weights, padding (-inf) and a collapsed ensemble alike.
    padded = np.log(w)
    padded[40:] = -np.inf
    for log_w in (np.log(w), padded, collapsed):
        np.testing.assert_allclose(
            ensemble.weighted_variance(jnp.asarray(x), jnp.asarray(log_w)),
            np.diag(ensemble.weighted_covariance(jnp.asarray(x), jnp.asarray(log_w))), rtol=1e-6)


def test_log_weight_normalisation_and_ess():
    raw = jnp.asarray([-1000.0, -1001.0, -1002.0, -jnp.inf])  # would underflow if exponentiated raw
    log_w, log_z = weights.normalise_log_weights(raw)
    w = np.exp([0.0, -1.0, -2.0])
    # float32 log-weights near -1000 carry an absolute error of about 1000 eps = 1.2e-4
    np.testing.assert_allclose(np.exp(log_w[:3]), w / w.sum(), rtol=3e-4)
    np.testing.assert_allclose(log_z, -1000.0 + np.log(w.sum()), rtol=1e-6)
    np.testing.assert_allclose(weights.effective_sample_size(log_w), 1 / np.sum((w / w.sum()) ** 2), rtol=1e-5)
    _, degenerate = weights.normalise_log_weights(jnp.full(3, -jnp.inf))
    assert not np.isfinite(degenerate)
    padded = weights.uniform_log_weights(jnp.zeros((5, 2)), 3)
    np.testing.assert_allclose(padded[:3], -np.log(3), rtol=1e-6)
    assert np.all(np.isneginf(padded[3:])) and int(weights.count_active(padded)) == 3


def test_active_first_is_the_stable_argsort_of_the_padding_flags():
    rng = np.random.default_rng(0)
    masks = [rng.random(50) < p for p in (0.0, 0.3, 0.8, 1.0)]
    for mask in masks:
        order = jax.jit(weights.active_first)(jnp.asarray(mask))
        np.testing.assert_array_equal(order, np.argsort(~mask, kind="stable"))


def test_use_where_picks_leaf_by_leaf():
    value = {"a": jnp.ones(3), "b": (jnp.full(2, 2.0),)}
    backup = {"a": jnp.zeros(3), "b": (jnp.full(2, -1.0),)}
    chosen = fallback.use_where(jnp.array(False), value, backup)
    np.testing.assert_array_equal(chosen["a"], 0.0)
    np.testing.assert_array_equal(chosen["b"][0], -1.0)
    rows = fallback.use_where(jnp.array([True, False, True]), jnp.ones(3), jnp.zeros(3))
    np.testing.assert_array_equal(rows, [1.0, 0.0, 1.0])


def _scaled(factor, x, *, power):
    return factor * x**power


def test_bind_compares_structure_by_value_and_traces_numbers():
    first, second = static.bind(_scaled, 2.0, power=2), static.bind(_scaled, 3.0, power=2)
    assert jax.tree.structure(first) == jax.tree.structure(second)
    assert jax.tree.structure(first) != jax.tree.structure(static.bind(_scaled, 2.0, power=3))
    assert jax.tree.leaves(first) == [2.0]
    traces = []

    @jax.jit
    def call(function, x):
        traces.append(None)
        return function(x)

    assert float(call(first, 3.0)) == 18.0 and float(call(second, 3.0)) == 27.0
    assert len(traces) == 1
    np.testing.assert_allclose(jax.vmap(lambda a: static.bind(_scaled, a, power=2)(2.0))(jnp.arange(3.0)), [0, 4, 8])
    with pytest.raises(TypeError):
        static.bind(_scaled, 1.0, power=[2])  # unhashable structure fails at build time


def test_validation_names_the_argument():
    with pytest.raises(ValueError, match="batch_size must be an int >= 2"):
        validation.check_int("batch_size", 1, minimum=2)
    with pytest.raises(ValueError, match="inflation must be >= 1"):
        validation.check_number("inflation", 0.5, minimum=1.0)
    with pytest.raises(ValueError, match="jitter must be finite"):
        validation.check_number("jitter", float("inf"), minimum=0.0)
    with pytest.raises(ValueError, match="initial_particles must be finite"):
        validation.check_finite_array("initial_particles", np.full((2, 2), np.nan))
    with pytest.raises(ValueError, match="estimate and truth must broadcast"):
        validation.check_broadcastable("estimate", np.zeros((3, 2)), "truth", np.zeros((4, 2)), True)
    assert validation.check_number("x", 2) == 2.0 and isinstance(validation.check_number("x", 2), float)
    jax.vmap(lambda a: validation.check_number("x", a, minimum=10.0))(jnp.ones(2))  # traced: unchecked
