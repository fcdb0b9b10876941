"""The OT update's small functions (transport/standardisation, batches, divergence and the
budget schedule) against direct NumPy computations."""

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.lib.ensemble import masked_mean_and_std

from ot_filter.lib.weights import active_mask, uniform_log_weights
from ot_filter.model import StateSpaceModel
from ot_filter.transport import batches, divergence, standardisation
from ot_filter.updates.ot import iteration_budget


def _ensemble(seed=0, num=9, n=2):
    return np.random.default_rng(seed).normal(size=(num, n)) * [1.0, 3.0] + [0.5, -2.0]


def test_standardisation_uses_active_rows_and_keeps_constant_coordinates():
    x = _ensemble()
    y = np.concatenate([x[:, :1] ** 2, np.full((9, 1), 4.0)], axis=1)  # second y coordinate constant
    active = np.arange(9) < 6
    scaling = standardisation.standardisation(jnp.asarray(x), jnp.asarray(y), jnp.asarray(active))
    np.testing.assert_allclose(scaling.x_mean, x[:6].mean(0), atol=1e-6)
    np.testing.assert_allclose(scaling.x_scale, x[:6].std(0), rtol=1e-5)
    np.testing.assert_allclose(scaling.y_scale, [y[:6, 0].std(), 1.0], rtol=1e-5)
    np.testing.assert_allclose(scaling.restore_x(scaling.standardise_x(jnp.asarray(x))), x, atol=1e-5)


def test_smoothed_prior_keeps_mean_and_covariance():
    x = jnp.asarray(np.random.default_rng(1).normal(size=(20000, 2)) @ np.array([[1.0, 0.8], [0.0, 0.6]]))
    x = (x - x.mean(0)) / x.std(0)
    factor = standardisation.correlation_cholesky(x)
    draws = standardisation.smoothed_draw(jax.random.key(0), x, 0.6, factor)
    # Monte-Carlo error of a correlation of 20,000 draws: about 1 / sqrt(20000) = 0.007
    np.testing.assert_allclose(np.cov(np.asarray(draws).T), np.cov(np.asarray(x).T), atol=0.03)
    h = standardisation.smoothing_bandwidth(1.0, 1000, 2, jnp.float32)
    np.testing.assert_allclose(h, (4 / 4) ** (1 / 6) * 1000 ** (-1 / 6), rtol=1e-6)
    assert float(standardisation.smoothing_bandwidth(100.0, 10, 2, jnp.float32)) == np.float32(standardisation.MAX_SMOOTHING_BANDWIDTH)


def test_batches_draw_active_particles_only():
    x = jnp.asarray(_ensemble(num=10))
    log_weights = uniform_log_weights(x, 4)
    active = active_mask(log_weights)
    scaling = standardisation.standardisation(x, x, active)
    data = batches.TrainingData(
        scaling.standardise_x(x), scaling.standardise_y(x), jnp.argsort(~active, stable=True),
        jnp.sum(active), jnp.asarray(0.5), None, scaling,
    )
    batch = batches.sample_batch(jax.random.key(0), data, lambda key, x: x, batch_size=500,
                                 smoothing=False, fresh_observations=False, enkf_layer=False)
    allowed = np.asarray(data.xs[:4])
    for rows in (batch.x, batch.xbar):
        assert all(np.any(np.all(np.isclose(row, allowed), axis=1)) for row in np.asarray(rows))
        assert len({tuple(row) for row in np.asarray(rows).round(5)}) == 4  # all four are drawn
    np.testing.assert_allclose(batch.y, batch.x, atol=1e-6)  # y = x pairs kept together


def test_own_pairs_are_the_first_active_pairs_with_the_next_as_copies():
    x = jnp.asarray(_ensemble(num=10))
    y = 2.0 * x + 1.0  # a pair's y tells its x
    active = jnp.asarray([False, True, True, False, True, True, True, False, True, True])
    index = jnp.argsort(~active, stable=True)
    data = batches.TrainingData(x, y, index, jnp.sum(active), jnp.asarray(0.5), None, None)
    rows = np.flatnonzero(np.asarray(active))  # the 7 active rows, in order
    batch = batches.own_pairs(data, 5)  # fewer than the active rows: the first 5, copies shifted
    np.testing.assert_array_equal(batch.x, x[rows[:5]])
    np.testing.assert_array_equal(batch.y, y[rows[:5]])
    np.testing.assert_array_equal(batch.xbar, x[rows[[1, 2, 3, 4, 0]]])
    np.testing.assert_array_equal(batch.ybar, y[rows[[1, 2, 3, 4, 0]]])
    batch = batches.own_pairs(data, 9)  # more than the active rows: they repeat, no inactive one
    np.testing.assert_array_equal(batch.x, x[rows[np.arange(9) % 7]])
    np.testing.assert_array_equal(batch.xbar, x[rows[(np.arange(9) + 1) % 7]])


def test_predictive_z_and_each_divergence_condition():
    x = jnp.asarray(_ensemble(num=50))
    active = jnp.ones(50, bool)
    y = jnp.asarray([1.0, 0.0])
    observe_state = StateSpaceModel(lambda key: jnp.zeros(2), lambda key, x: x, lambda key, x: x)
    z = divergence.predictive_z(jax.random.key(0), observe_state, x, y, active)
    expected = np.max(np.abs(np.asarray(y) - np.asarray(x).mean(0)) / np.asarray(x).std(0))
    np.testing.assert_allclose(z, expected, rtol=1e-5)
    moved = (x - x.mean(0)) / x.std(0) * 0.5
    prior = (x - x.mean(0)) / x.std(0)
    healthy = dict(trace_finite=jnp.array(True), smoothed_loss=jnp.asarray(1.0), threshold=10.0, n=2,
                   moved_standard=moved, active=active, z=jnp.asarray(2.0), prior_standard=prior)
    assert not bool(divergence.diverged(**healthy))
    for change in (dict(trace_finite=jnp.array(False)), dict(smoothed_loss=jnp.asarray(25.0)),
                   dict(moved_standard=moved.at[3, 1].set(jnp.nan)), dict(moved_standard=moved * 30),
                   dict(z=jnp.asarray(11.0)),
                   # one particle thrown 7 prior stds away: the spread (1.2) does not show it
                   dict(moved_standard=moved.at[7, 0].set(7.0))):
        assert bool(divergence.diverged(**{**healthy, **change})), change
    _, spread = masked_mean_and_std(moved.at[7, 0].set(7.0), active)
    assert float(spread.max()) < divergence.MAX_POSTERIOR_SPREAD
    # ... but not a particle that was already that far out in the prior (a Lorenz-63 forecast
    # has particles 8 stds out) and stays within TRANSPORT_MARGIN of where it was
    far_prior = prior.at[7, 0].set(8.0)
    margin = divergence.TRANSPORT_MARGIN
    assert not bool(divergence.diverged(**{**healthy, "prior_standard": far_prior,
                                          "moved_standard": moved.at[7, 0].set(8.0 + margin - 0.1)}))
    assert bool(divergence.diverged(**{**healthy, "prior_standard": far_prior,
                                      "moved_standard": moved.at[7, 0].set(8.0 + margin + 0.1)}))
    # the reach is per particle (no ratchet from the prior's outliers) and per coordinate
    assert bool(divergence.diverged(**{**healthy, "prior_standard": far_prior, "moved_standard": moved.at[8, 0].set(7.0)}))
    assert bool(divergence.diverged(**{**healthy, "prior_standard": far_prior, "moved_standard": moved.at[7, 1].set(7.0)}))
    # non-finite padding rows do not count
    assert not bool(divergence.diverged(**{**healthy, "moved_standard": moved.at[3].set(jnp.inf),
                                          "active": active.at[3].set(False)}))


def test_iteration_budget_halves_down_to_the_floor():
    budgets = [int(iteration_budget(jnp.asarray(k), 1024, 64)) for k in range(7)]
    assert budgets == [1024, 512, 256, 128, 64, 64, 64]
    assert int(iteration_budget(jnp.asarray(100), 1024, 64)) == 64


def test_gaussian_transport_matrix_maps_one_covariance_onto_the_other_and_moves_least(x64):
    import scipy.linalg

    from ot_filter.lib.gaussian import gaussian_transport_matrix

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(4, 4)), rng.normal(size=(4, 4))
    prior, target = a @ a.T + 0.1 * np.eye(4), b @ b.T + 0.1 * np.eye(4)
    matrix = np.asarray(gaussian_transport_matrix(jnp.asarray(prior), jnp.asarray(target)))
    np.testing.assert_allclose(matrix @ prior @ matrix.T, target, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(matrix, matrix.T, atol=1e-12)
    assert np.linalg.eigvalsh(matrix).min() > 0  # the OT map is the gradient of a convex function
    root = scipy.linalg.sqrtm(prior).real
    inverse_root = np.linalg.inv(root)
    expected = inverse_root @ scipy.linalg.sqrtm(root @ target @ root).real @ inverse_root
    np.testing.assert_allclose(matrix, expected, rtol=1e-8, atol=1e-8)
    # In one dimension: the ratio of standard deviations.
    np.testing.assert_allclose(gaussian_transport_matrix(jnp.array([[4.0]]), jnp.array([[1.0]])), [[0.5]])


def test_deterministic_layer_gives_the_kalman_posterior_moments_of_its_own_sample(x64):
    from ot_filter.transport.saddle import deterministic_layer, enkf_gain, transport_input

    key_x, key_h, key_v = jax.random.split(jax.random.PRNGKey(0), 3)
    num, n, m = 500, 3, 2
    x = jax.random.normal(key_x, (num, n)) @ jnp.array([[1.0, 0.5, 0.2], [0.0, 1.0, 0.3], [0.0, 0.0, 0.7]]) + 1.0
    y = jnp.tanh(x[:, :m]) + 0.3 * jax.random.normal(key_v, (num, m))  # nonlinear: moments only
    layer = deterministic_layer(x, y)
    np.testing.assert_allclose(layer.gain, enkf_gain(x, y), rtol=1e-12)  # the same gain as the perturbed layer
    observation = jnp.array([0.5, -0.2])
    moved = np.asarray(transport_input(x, jnp.broadcast_to(observation, y.shape), y * np.nan, layer))
    X, Y = np.asarray(x), np.asarray(y)
    cov = np.cov(np.concatenate([X, Y], axis=1).T)
    cov_x, cross, cov_y = cov[:n, :n], cov[:n, n:], cov[n:, n:]
    gain = cross @ np.linalg.inv(cov_y)
    # The sample's Kalman posterior, up to the relative ridge (1e-4): ybar is not read (NaN above).
    np.testing.assert_allclose(moved.mean(axis=0), X.mean(0) + gain @ (np.asarray(observation) - Y.mean(0)),
                               atol=1e-3)
    np.testing.assert_allclose(np.cov(moved.T), cov_x - gain @ cross.T, atol=2e-3)


def test_ot_with_an_untrained_map_and_the_deterministic_layer_is_the_sample_kalman_posterior(x64):
    """T starts as the identity: with a negligible learning rate the global update is its
    deterministic layer, whose particles have the sample Kalman mean and covariance (to the
    1e-4 ridge) in the update's own simulated observations."""
    import ot_filter as otf
    from conftest import random_linear_gaussian

    model = otf.models.linear_gaussian(*random_linear_gaussian(3))
    prior = jax.vmap(model.sample_initial)(jax.random.split(jax.random.PRNGKey(0), 400))
    update = otf.ot(num_iterations=1, enkf_layer="deterministic", transport_learning_rate=1e-12,
                    concavity_points=0)
    state = update.init(jax.random.PRNGKey(1), prior, model)
    observation = jnp.array([0.3, -0.4])
    posterior, state, info = update.apply(jax.random.PRNGKey(2), state, prior, observation, model)
    X, Y = np.asarray(prior), np.asarray(state.simulated_observations)
    cov = np.cov(np.concatenate([X, Y], axis=1).T)
    n = X.shape[1]
    gain = cov[:n, n:] @ np.linalg.inv(cov[n:, n:])
    np.testing.assert_allclose(np.mean(posterior, axis=0), X.mean(0) + gain @ (np.asarray(observation) - Y.mean(0)),
                               atol=2e-3)
    np.testing.assert_allclose(np.cov(np.asarray(posterior).T), cov[:n, :n] - gain @ cov[:n, n:].T, atol=2e-3)


def test_the_known_noise_gain_is_the_dense_formula_and_survives_a_singular_innovation():
    from ot_filter.transport.saddle import known_noise_gain

    x = jax.random.normal(jax.random.key(0), (200, 3))
    predicted = x[:, :2] ** 2 + 0.1 * jax.random.normal(jax.random.key(1), (200, 2))
    noise = jnp.array([[0.5, 0.2], [0.2, 0.3]])
    xc, hc = np.asarray(x - x.mean(0), np.float64), np.asarray(predicted - predicted.mean(0), np.float64)
    cross, cov_h = xc.T @ hc / 199, hc.T @ hc / 199
    np.testing.assert_allclose(known_noise_gain(x, predicted, noise), np.linalg.solve(cov_h + noise, cross.T).T,
                               rtol=1e-4, atol=1e-5)
    # 3 particles for 8 components and R = 0: Cov(h) + R has rank 2, its Cholesky factor is NaN in
    # float32; the gain is then the one with the relative ridge 1e-4 (1 + tr / m), and finite.
    x, predicted = jax.random.normal(jax.random.key(2), (3, 8)), jax.random.normal(jax.random.key(3), (3, 8))
    gain = known_noise_gain(x, predicted, jnp.zeros((8, 8)))
    xc, hc = np.asarray(x - x.mean(0), np.float64), np.asarray(predicted - predicted.mean(0), np.float64)
    cross, cov_h = xc.T @ hc / 2, hc.T @ hc / 2
    ridged = cov_h + 1e-4 * (1 + np.trace(cov_h) / 8) * np.eye(8)
    assert np.all(np.isfinite(np.asarray(gain)))
    np.testing.assert_allclose(gain, np.linalg.solve(ridged, cross.T).T, rtol=2e-3, atol=2e-3)


def test_wider_than_enkf_compares_each_coordinate_s_spread_over_the_active_rows():
    base = jax.random.normal(jax.random.key(4), (400, 2))
    enkf = base * jnp.array([1.0, 2.0])
    active = jnp.arange(400) < 300
    limit = divergence.MAX_SPREAD_OVER_ENKF
    for factor, expected in ((0.98, False), (1.02, True)):
        # the second coordinate at factor x the bound, the padding (inactive rows) far off
        moved = (base * jnp.array([1.0, 2.0 * limit * factor])).at[300:].set(1e6)
        assert bool(divergence.wider_than_enkf(moved, enkf.at[300:].set(-1e6), active)) == expected
    assert not bool(divergence.wider_than_enkf(0.5 * enkf, enkf, active))
