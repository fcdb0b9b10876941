"""Partial observations: NaN components of y are missing and the others are assimilated.

The reference is always the same model with those rows of h and R deleted: the Kalman filter
exactly (float64, 1e-10), the ensemble updates under the same key (the draws that remain are
the same ones: jax.random streams are prefix-consistent, so trailing components are deleted),
and the OT update against the Kalman posterior of the deleted-rows model.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.models import linear_gaussian


def _random_linear_gaussian(seed, n=3, m=4, correlated=True):
    rng = np.random.default_rng(seed)
    A = 0.9 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    Q = 0.3 * np.eye(n)
    H = rng.normal(size=(m, n))
    B = rng.normal(size=(m, m))
    R = (0.5 * B @ B.T / m + 0.5 * np.eye(m)) if correlated else np.diag(rng.uniform(0.3, 1.0, m))
    return A, Q, H, R, np.zeros(n), np.eye(n)


def _delete_rows(parameters, observed):
    A, Q, H, R, m0, P0 = parameters
    return A, Q, H[observed], R[np.ix_(observed, observed)], m0, P0


def _kalman_reference(parameters, observations):
    """Dense NumPy Kalman filter deleting the missing rows at each step (float64)."""
    A, Q, H, R, mean, cov = (np.asarray(p, np.float64) for p in parameters)
    means, log_likelihood = [], 0.0
    for y in np.asarray(observations):
        mean, cov = A @ mean, A @ cov @ A.T + Q
        o = np.isfinite(y)
        if o.any():
            Ho, Ro = H[o], R[np.ix_(o, o)]
            S = Ho @ cov @ Ho.T + Ro
            K = cov @ Ho.T @ np.linalg.inv(S)
            r = y[o] - Ho @ mean
            log_likelihood += -0.5 * (o.sum() * np.log(2 * np.pi) + np.linalg.slogdet(S)[1]
                                      + r @ np.linalg.solve(S, r))
            mean = mean + K @ r
            cov = (np.eye(len(mean)) - K @ Ho) @ cov
        means.append(mean)
    return np.array(means), log_likelihood


def test_kalman_with_nan_rows_equals_kalman_with_rows_deleted(x64):
    parameters = _random_linear_gaussian(0)
    model = linear_gaussian(*parameters)
    _, observations = otf.simulate(jax.random.key(1), model, 40)
    observations = np.array(observations)
    # A time-varying pattern: nothing, one, several and all components missing.
    rng = np.random.default_rng(2)
    observations[rng.random(observations.shape) < 0.35] = np.nan
    observations[5] = np.nan
    result = otf.kalman_filter(model, observations)
    means, log_likelihood = _kalman_reference(parameters, observations)
    np.testing.assert_allclose(result.mean, means, rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.log_likelihood, log_likelihood, rtol=1e-12)
    # The same missing set at every step: the Kalman filter of the deleted-rows model.
    observed = np.array([True, False, True, False])
    fixed = np.array(observations)
    fixed[:, ~observed] = np.nan
    deleted = otf.kalman_filter(linear_gaussian(*_delete_rows(parameters, observed)),
                                fixed[:, observed])
    full = otf.kalman_filter(model, fixed)
    rows = np.all(np.isfinite(fixed[:, observed]), axis=1)
    assert rows.sum() > 10
    np.testing.assert_allclose(full.mean, deleted.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(full.cov, deleted.cov, rtol=0, atol=1e-10)
    np.testing.assert_allclose(full.log_likelihood, deleted.log_likelihood, rtol=1e-12)


def _ensemble(seed, num, n):
    return jax.random.normal(jax.random.key(seed), (num, n)) @ jnp.diag(jnp.arange(1.0, n + 1.0))


# A simulator of correlated noise cannot keep the kept components' draws when rows are deleted,
# so the simulation-based EnKF is checked with independent noise only.
@pytest.mark.parametrize("update,correlated", [
    ("sqrt", True), ("sqrt", False), ("sqrt_rotate", True), ("sqrt_rotate", False),
    ("perturbed", True), ("perturbed", False),
    ("simulated", False), ("sir", True), ("sir", False),
])
def test_ensemble_update_with_trailing_nan_equals_deleted_rows(x64, update, correlated):
    parameters = _random_linear_gaussian(3, correlated=correlated)
    model = linear_gaussian(*parameters)
    observed = np.array([True, True, False, False])
    deleted = linear_gaussian(*_delete_rows(parameters, observed))
    if update == "simulated":  # the simulation-based EnKF (no h, no R)
        # Each component's noise from its own key, so that the deleted-rows simulator draws the
        # same noise on the components it keeps.
        _, _, H, R, _, _ = parameters

        def simulator(components):
            def sample(key, x):
                noise = jax.vmap(lambda i: jax.random.normal(jax.random.fold_in(key, i)))(components)
                return H[components] @ x + np.sqrt(np.diag(R))[components] * noise
            return sample

        model = model._replace(observation_function=None, observation_noise_cov=None,
                               sample_observation=simulator(np.arange(4)))
        deleted = deleted._replace(observation_function=None, observation_noise_cov=None,
                                   sample_observation=simulator(np.flatnonzero(observed)))
    builder = {
        "sqrt": lambda: otf.enkf(inflation=1.1, perturbed=False),
        "sqrt_rotate": lambda: otf.enkf(inflation=1.1, perturbed=False, rotate=True),
        "perturbed": lambda: otf.enkf(inflation=1.1),
        "simulated": lambda: otf.enkf(inflation=1.1),
        "sir": lambda: otf.sir(ess_threshold=1.0),
    }[update]()
    particles = _ensemble(4, 30, 3)
    y = jnp.asarray([0.3, -1.2, 7.0, -9.0])
    y_missing = y.at[~observed].set(jnp.nan)
    state = builder.init(jax.random.key(5), particles, model)
    key = jax.random.key(6)
    posterior, new_state, _ = builder.apply(key, state, particles, y_missing, model)
    reference, reference_state, _ = builder.apply(key, state, particles, y[observed], deleted)
    assert np.all(np.isfinite(posterior))
    np.testing.assert_allclose(posterior, reference, rtol=0, atol=1e-10)
    np.testing.assert_allclose(new_state.log_weights, reference_state.log_weights, atol=1e-10)
    # And the missing entries' values never matter: a different h there changes nothing.
    if update in ("sqrt", "sqrt_rotate", "perturbed"):
        bump = jnp.where(jnp.asarray(observed), 0.0, 5.0)
        shifted = model._replace(
            observation_function=lambda x: parameters[2] @ x + bump * jnp.sin(x[0]))
        moved, _, _ = builder.apply(key, state, particles, y_missing, shifted)
        np.testing.assert_allclose(moved, posterior, rtol=0, atol=1e-9)


def test_letkf_with_nan_equals_deleted_rows_for_any_missing_set(x64):
    model = otf.models.lorenz96(dim=12, observation_noise_std=0.7)
    observed = np.array([0, 1, 2, 4, 5, 7, 8, 9, 11])  # 3, 6 and 10 missing
    deleted = otf.models.lorenz96(dim=12, observation_noise_std=0.7, observed=observed)
    particles = 2.0 + _ensemble(7, 8, 12)
    y = jnp.asarray(np.random.default_rng(8).normal(size=12))
    y_missing = y.at[np.setdiff1d(np.arange(12), observed)].set(jnp.nan)
    update = otf.letkf(otf.localisation(model.geometry, 2.0), inflation=1.05)
    reference_update = otf.letkf(otf.localisation(deleted.geometry, 2.0), inflation=1.05)
    state = update.init(jax.random.key(0), particles, model)
    posterior, _, _ = update.apply(jax.random.key(1), state, particles, y_missing, model)
    reference, _, _ = reference_update.apply(jax.random.key(1), state, particles, y[observed], deleted)
    np.testing.assert_allclose(posterior, reference, rtol=0, atol=1e-10)
    assert not np.allclose(posterior, particles)


@pytest.mark.long
def test_ot_update_with_a_missing_component_matches_the_deleted_rows_kalman_posterior():
    # x ~ N(0, I_2), y = x + noise (2 components), the second one missing: the posterior is that
    # of the first observation alone, x_0 | y_0 ~ N(0.8, 0.2), and x_1 ~ N(0, 1) unmoved.
    model = linear_gaussian(np.eye(2), np.zeros((2, 2)), np.eye(2), 0.25 * np.eye(2), np.zeros(2),
                            np.eye(2))
    num = 2000
    particles = jax.random.normal(jax.random.key(0), (num, 2))
    update = otf.ot(num_iterations=6000)
    state = update.init(jax.random.key(1), particles, model)
    posterior, _, info = update.apply(jax.random.key(2), state, particles,
                                      jnp.asarray([1.0, jnp.nan]), model)
    assert not bool(info.diverged)
    mean, std = np.mean(posterior, axis=0), np.std(posterior, axis=0)
    # Monte-Carlo floor of the means: std / sqrt(N) (0.01 and 0.022); of the stds: std / sqrt(2N).
    # The OT map's own error at this budget is measured with the deleted-rows model (same
    # numbers: std 0.451 with the row deleted, 0.450 with NaN), hence the 5 % on the stds.
    np.testing.assert_allclose(mean, [0.8, 0.0], atol=4 * 1.0 / np.sqrt(num))
    np.testing.assert_allclose(std, [np.sqrt(0.2), 1.0], rtol=0.05)


def test_run_filter_partial_observations_do_not_recompile_and_skip_only_empty_rows():
    from ot_filter.filtering import _run_filter

    model = otf.models.lorenz96(dim=8)
    truth, observations = otf.simulate(jax.random.key(0), model, 30)
    update = otf.letkf(otf.localisation(model.geometry, 2.0), inflation=1.02)
    rng = np.random.default_rng(0)
    first = np.array(observations)
    first[rng.random(first.shape) < 0.5] = np.nan
    first[3] = np.nan
    result = otf.run_filter(jax.random.key(1), model, update, first, 16, save_every=0)
    size = _run_filter._cache_size()
    second = np.array(observations)
    second[rng.random(second.shape) < 0.3] = np.nan
    again = otf.run_filter(jax.random.key(1), model, update, second, 16, save_every=0)
    assert _run_filter._cache_size() == size
    np.testing.assert_array_equal(result.observed, np.any(np.isfinite(first), axis=1))
    assert not bool(result.observed[3])
    assert np.all(np.isfinite(result.mean)) and np.all(np.isfinite(again.mean))
