"""The localised OT update, its windows, and the honest accuracy metrics.

Closed forms first: windows against brute force and lattice consistency; the local EnKF layer
(the update's fallback) against a dense per-coordinate perturbed-observation EnKF; a window that
covers the whole state against the global gain; the metrics against translations and exact
samples. Then accuracy against the exact posterior of the chapter's static example.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter import metrics
from ot_filter.localisation import local_windows, points, ring, taper_support
from ot_filter.models import squared_observation
from ot_filter.reference import squared_observation_posterior
from ot_filter.transport.saddle import enkf_gain, transport_input
from ot_filter.transport.standardisation import Standardisation
from ot_filter.updates.local_ot import (
    LocalOTSettings,
    _fresh_slots,
    _layer_weights,
    local_data,
    move_windows,
    local_ot,
    local_prior_quantiles,
    sort_columns,
    tabulated,
)


def test_windows_match_brute_force_and_mean_the_same_offsets_on_a_ring():
    size, observed = 12, np.arange(0, 12, 3)
    windows = local_windows(ring(size, observed), radius=2.0, state_radius=1.0)
    state, observations = np.asarray(windows.state), np.asarray(windows.observations)
    for i in range(size):
        gaps = (np.arange(size) - i + size // 2) % size - size // 2  # signed ring offsets
        expected_state = sorted(np.nonzero(np.abs(gaps) <= 1)[0], key=lambda j: (abs(gaps[j]), j != i, gaps[j]))
        assert list(state[i]) == expected_state
        near = [k for k, j in enumerate(observed) if abs(gaps[j]) <= 2]
        got = observations[i][np.asarray(windows.observations_valid[i])]
        assert list(got) == sorted(near, key=lambda k: (abs(gaps[observed[k]]), gaps[observed[k]]))
    # Slot k sits at the same offset for every coordinate: -1 then +1 in the state window.
    offsets = (state - np.arange(size)[:, None] + size // 2) % size - size // 2
    assert np.all(offsets == np.array([0, -1, 1]))


def test_windows_on_a_periodic_plane_keep_the_lattice_order():
    side = 5
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)
    windows = local_windows(points(grid, grid, period=side), radius=1.0, state_radius=1.0)
    shifts = grid[np.asarray(windows.state)] - grid[:, None, :]
    shifts = (shifts + side // 2) % side - side // 2
    assert windows.state.shape == (side * side, 5)
    assert np.all(shifts == shifts[0])  # one stencil everywhere, the coordinate itself first
    assert np.all(shifts[0, 0] == 0)
    np.testing.assert_array_equal(windows.observations, windows.state)


def test_radius_zero_windows_are_each_coordinates_own_observation():
    model = squared_observation(dim=6)
    windows = local_windows(model.geometry, 0.0)
    np.testing.assert_array_equal(windows.state, np.arange(6)[:, None])
    np.testing.assert_array_equal(windows.observations, np.arange(6)[:, None])


def test_per_row_gains_equal_one_gain_per_row():
    key = jax.random.PRNGKey(0)
    xbar, y, ybar = (jax.random.normal(k, (7, s)) for k, s in zip(jax.random.split(key, 3), (3, 4, 4)))
    gains = jax.random.normal(jax.random.PRNGKey(1), (7, 3, 4))
    expected = jnp.stack([transport_input(xbar[b:b + 1], y[b:b + 1], ybar[b:b + 1], gains[b])[0] for b in range(7)])
    np.testing.assert_allclose(transport_input(xbar, y, ybar, gains), expected, rtol=1e-6, atol=1e-6)


def _numbers(windows, levels=0):
    return LocalOTSettings(None, windows, (jnp.arange(levels) + 0.5) / max(levels, 1),
                           _layer_weights(windows, "step"))


def _ring_data(key, num, size, observed, radius, state_radius):
    geometry = ring(size, observed)
    windows = local_windows(geometry, radius, state_radius)
    xs = jax.random.normal(key, (num, size), jnp.float64)
    mixing = jnp.eye(size) + 0.5 * jnp.roll(jnp.eye(size), 1, axis=1)
    xs = xs @ mixing  # correlated neighbours
    ys = xs[:, observed] + 0.3 * jax.random.normal(jax.random.fold_in(key, 1), (num, len(observed)), jnp.float64)
    y = jnp.linspace(-1.0, 1.0, len(observed))
    return windows, xs, ys, y


def test_local_enkf_layer_is_the_per_coordinate_perturbed_enkf(x64):
    num, size, observed = 50, 10, np.arange(0, 10, 2)
    windows, xs, ys, y = _ring_data(jax.random.PRNGKey(2), num, size, observed, 2.0, 1.0)
    active = jnp.ones(num, bool)
    data = local_data(_numbers(windows), xs, ys, y, jnp.ones(len(observed), bool), active)
    moved = np.asarray(move_windows(data, None, True, windows.observations.shape[1]))
    X, Y = np.asarray(xs), np.asarray(ys)
    for i in range(size):
        state = np.asarray(windows.state[i])
        near = np.asarray(windows.observations[i])[np.asarray(windows.observations_valid[i])]
        xa, ya = X[:, state] - X[:, state].mean(0), Y[:, near] - Y[:, near].mean(0)
        cov_y = ya.T @ ya / (num - 1)
        ridge = 1e-4 * (1 + np.trace(cov_y) / windows.observations.shape[1])  # over the K slots
        gain = (xa.T @ ya / (num - 1)) @ np.linalg.inv(cov_y + ridge * np.eye(len(near)))
        expected = X[:, i] + (np.asarray(y)[near] - Y[:, near]) @ gain[0]
        np.testing.assert_allclose(moved[:, i], expected, rtol=1e-6, atol=1e-6)


def test_a_window_over_everything_has_the_global_gain(x64):
    num, size, observed = 40, 6, np.arange(6)
    windows, xs, ys, y = _ring_data(jax.random.PRNGKey(3), num, size, observed, 10.0, 10.0)
    data = local_data(_numbers(windows), xs, ys, y, jnp.ones(size, bool), jnp.ones(num, bool))
    global_gain = enkf_gain(xs, ys)  # [n, m]
    for i in range(size):
        state, near = np.asarray(windows.state[i]), np.asarray(windows.observations[i])
        reach = near.size
        # The same ridge (relative to the m slots' mean variance): the same gain.
        np.testing.assert_allclose(data.gain[i][:, :reach], np.asarray(global_gain)[np.ix_(state, near)],
                                   rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(data.gain[i][:, reach:], 0.0, atol=1e-12)


def _static_problem(dim, num=1000, seed=0):
    model = squared_observation(dim=dim, noise=0.4, observation_scale=0.5, static=True)
    prior = jax.vmap(model.sample_initial)(jax.random.split(jax.random.PRNGKey(seed), num))
    exact = squared_observation_posterior(1.0, 0.4, scale=0.5)
    masses = jnp.broadcast_to(exact.density, (dim,) + exact.density.shape)
    return model, prior, exact.grid, masses


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_columns_sorted_as_integers_are_sorted_as_floats(x64, dtype):
    values = jnp.array([[3.5, -0.0], [-1e-30, 0.0], [-2.0, jnp.inf], [1e30, -jnp.inf], [-7.25, 1.0], [0.0, -1.0]],
                       dtype)
    values = jnp.concatenate([values, jax.random.normal(jax.random.PRNGKey(0), (200, 2), dtype) * 10.0])
    ordered = sort_columns(values)
    assert ordered.dtype == dtype
    np.testing.assert_array_equal(ordered, np.sort(np.asarray(values), axis=0))


def test_the_prior_context_is_each_window_coordinates_quantiles_and_gets_no_gain(x64):
    num, size, observed = 60, 8, np.arange(8)
    windows, xs, ys, y = _ring_data(jax.random.PRNGKey(4), num, size, observed, 1.0, 1.0)
    active = jnp.arange(num) < 50  # padding rows do not count
    levels = 4
    quantiles = np.asarray(local_prior_quantiles(xs, active, (jnp.arange(levels) + 0.5) / levels))
    ordered = np.sort(np.asarray(xs)[:50], axis=0)
    np.testing.assert_array_equal(quantiles, ordered[np.floor((np.arange(levels) + 0.5) / levels * 50).astype(int)].T)
    data = local_data(_numbers(windows, levels), xs, ys, y, jnp.ones(size, bool), active)
    reach, window = windows.observations.shape[1], windows.state.shape[1]
    context = np.asarray(data.y)[:, :, 2 * reach:]  # [N, n, S Q]
    np.testing.assert_array_equal(context, np.broadcast_to(context[0], context.shape))  # one per coordinate
    deviations = quantiles - quantiles.mean(axis=0)  # from the coordinates' mean profile
    np.testing.assert_allclose(context[0].reshape(size, window, levels), deviations[np.asarray(windows.state)],
                               atol=1e-12)
    np.testing.assert_allclose(np.asarray(data.gain)[:, :, 2 * reach:], 0.0, atol=1e-10)


def test_fresh_observations_are_h_of_the_pair_plus_the_windows_noise_and_keep_the_rest(x64):
    """``fresh_observations``: a pair's observation slots redrawn as h(X)_O + noise of R[O, O]
    (a correlated R here), masked slots (padding, missing components) 0, the mask and context
    columns as simulated. Monte Carlo over 20,000 draws of one pair: mean and covariance within
    five standard errors."""
    num, size, observed = 30, 10, np.arange(0, 10, 2)
    windows, xs, ys, y = _ring_data(jax.random.PRNGKey(5), num, size, observed, 4.0, 0.0)
    present = jnp.array([True, True, False, True, True])  # a missing component
    predicted = xs[:, observed] * 0.8 + 0.1
    sd = jnp.array([0.3, 0.5, 0.2, 0.4, 0.1])
    correlation = 0.6 ** jnp.abs(jnp.arange(5)[:, None] - jnp.arange(5)[None, :])
    covariance = correlation * jnp.outer(sd, sd)
    data = local_data(_numbers(windows, 2), xs, jnp.where(present, ys, 0.0), jnp.where(present, y, 0.0), present,
                       jnp.ones(num, bool), fresh=(predicted, covariance))
    reach = windows.observations.shape[1]
    draws, pair, coordinate = 20_000, 7, 3
    rows, coordinates = jnp.full((draws,), pair), jnp.full((draws,), coordinate)
    fresh = np.asarray(_fresh_slots(jax.random.PRNGKey(6), data, rows, coordinates, data.y[rows, coordinates]))
    slots = np.asarray(windows.observations[coordinate])
    mask = np.asarray(windows.observations_valid[coordinate]) & np.asarray(present)[slots]
    assert 0 < mask.sum() < reach  # padding or the missing component among the slots
    block = np.asarray(covariance)[np.ix_(slots, slots)] * np.outer(mask, mask)
    expected = np.where(mask, np.asarray(predicted)[pair, slots], 0.0)
    np.testing.assert_allclose(fresh[:, :reach].mean(axis=0), expected, atol=5 * np.sqrt(block.max() / draws))
    variances = np.diag(block)
    stderr = np.sqrt((np.outer(variances, variances) + block**2) / draws)  # of a sample covariance
    assert np.all(np.abs(np.cov(fresh[:, :reach].T) - block) <= 5 * stderr + 1e-12)
    assert np.all(fresh[:, :reach][:, ~mask] == 0.0)
    assert np.abs(block[mask][:, mask] - np.diag(variances[mask])).max() > 0.01  # the test sees correlation
    np.testing.assert_array_equal(fresh[:, reach:], np.broadcast_to(np.asarray(data.y)[pair, coordinate, reach:],
                                                                    (draws, fresh.shape[1] - reach)))


@pytest.mark.parametrize("enkf_layer", [False, "perturbed", "deterministic"])
def test_fresh_observations_change_the_training_not_the_rest(enkf_layer):
    """With each layer the option reaches the training (another map from the same keys) and the
    update stays finite; the experiments pass it on to the localised update."""
    model, prior, _, _ = _static_problem(3, num=200)
    outputs = []
    for fresh in (False, True):
        update = local_ot(local_windows(model.geometry, 0.0), num_iterations=50, enkf_layer=enkf_layer,
                          fresh_observations=fresh)
        state = update.init(jax.random.PRNGKey(0), prior, model)
        posterior, _, info = update.apply(jax.random.PRNGKey(1), state, prior, jnp.ones(3), model)
        assert not bool(info.diverged) and bool(jnp.all(jnp.isfinite(posterior)))
        outputs.append(np.asarray(posterior))
    assert np.abs(outputs[0] - outputs[1]).max() > 1e-3
    from ot_filter.experiments._common import make_updates
    from ot_filter.updates.local_ot import local_update_parts
    for options, expected in ((None, False), ({"fresh_observations": True}, True)):
        built = make_updates(["local_ot"], options, model=model, radius=0.0)["local_ot"]
        assert local_update_parts(built)[1].fresh_observations is expected


def test_the_location_context_is_each_windows_mean_and_spread_in_model_coordinates(x64):
    """Per window: arcsinh of the mean and log of the spread of its state coordinates, then of
    its observations (0 on a missing one), after the quantiles; constant over the particles, so
    no gain. A model coordinate's location is what standardisation removes and y = x^2 needs."""
    num, size, observed = 60, 8, np.arange(0, 8, 2)
    windows, xs, ys, y = _ring_data(jax.random.PRNGKey(4), num, size, observed, 2.0, 1.0)
    scaling = Standardisation(jnp.linspace(-5.0, 9.0, size), jnp.linspace(0.5, 2.0, size),
                              jnp.linspace(1.0, 80.0, len(observed)), jnp.linspace(3.0, 30.0, len(observed)))
    seen = jnp.ones(len(observed), bool).at[1].set(False)
    data = local_data(_numbers(windows, 2), xs, ys, y, seen, jnp.ones(num, bool), location=scaling)
    reach, window = windows.observations.shape[1], windows.state.shape[1]
    features = np.asarray(data.y)[:, :, 2 * reach + 2 * window:]  # [N, n, 2 (S + K)]
    np.testing.assert_array_equal(features, np.broadcast_to(features[0], features.shape))
    state, slots = np.asarray(windows.state), np.asarray(windows.observations)
    mask = np.asarray(windows.observations_valid) & np.asarray(seen)[slots]
    expected = np.concatenate([np.arcsinh(np.asarray(scaling.x_mean))[state],
                               np.log(np.asarray(scaling.x_scale))[state],
                               np.where(mask, np.arcsinh(np.asarray(scaling.y_mean))[slots], 0.0),
                               np.where(mask, np.log(np.asarray(scaling.y_scale))[slots], 0.0)], axis=1)
    np.testing.assert_allclose(features[0], expected, atol=1e-12)
    np.testing.assert_allclose(np.asarray(data.gain)[:, :, 2 * reach:], 0.0, atol=1e-10)
    # The networks' input grows by those 2 (S + K) columns.
    model = otf.models.lorenz96(dim=size, observed=observed)
    prior = jax.random.normal(jax.random.PRNGKey(0), (30, size))
    plain, located = (local_ot(local_windows(model.geometry, 2.0, 1.0), location_context=flag).init(
        jax.random.PRNGKey(0), prior, model).gain.shape[-1] for flag in (False, True))
    assert located - plain == 2 * (window + reach)


def test_divergence_falls_back_to_the_local_enkf():
    model, prior, _, _ = _static_problem(3, num=200)
    update = local_ot(local_windows(model.geometry, 0.0), num_iterations=20, divergence_threshold=1e-9)
    state = update.init(jax.random.PRNGKey(0), prior, model)
    posterior, state, info = update.apply(jax.random.PRNGKey(1), state, prior, jnp.ones(3), model)
    assert bool(info.diverged) and bool(state.diverged)
    assert np.all(np.isfinite(posterior))
    # The fallback is the layer alone with the update's own simulated observations.
    scaling = state.standardisation
    observed = jnp.ones(3, bool)
    data = local_data(_numbers(local_windows(model.geometry, 0.0), 8), scaling.standardise_x(prior),
                       scaling.standardise_y(state.simulated_observations), scaling.standardise_y(jnp.ones(3)),
                       observed, jnp.ones(200, bool))
    np.testing.assert_allclose(posterior, scaling.restore_x(move_windows(data, None, True, 1)), rtol=1e-5, atol=1e-5)


def test_a_tabulated_map_is_exact_where_linear_and_within_half_a_knot_step_at_a_kink(x64):
    """Linear interpolation of an L-Lipschitz function errs by at most L h / 2 (h the knot step)
    and not at all on a knot interval where it is linear: exact for a line, and for |u - c| only
    in the interval that holds c. Inactive rows do not widen the knots' span."""
    u = jax.random.normal(jax.random.PRNGKey(0), (500,))
    active = jnp.arange(500) < 450
    u = jnp.where(active, u, 1e6)  # padding far away
    knots = 33
    line = tabulated(lambda v: 3.0 * v - 1.0, u, active, knots)
    np.testing.assert_allclose(line[:450], 3.0 * u[:450] - 1.0, rtol=0, atol=1e-12)
    kink = 0.1234
    step = float(jnp.max(u[:450]) - jnp.min(u[:450])) / (knots - 1)
    error = np.abs(np.asarray(tabulated(lambda v: jnp.abs(v - kink), u, active, knots) - jnp.abs(u - kink)))[:450]
    assert error.max() <= step / 2 + 1e-12
    interval = np.floor((np.asarray(u[:450]) - float(jnp.min(u[:450]))) / step)
    holding_kink = interval == np.floor((kink - float(jnp.min(u[:450]))) / step)
    assert error[holding_kink].max() > 1e-3 and error[~holding_kink].max() < 1e-12
    assert np.isfinite(np.asarray(line)).all()  # padding clamped to the last knot, not extrapolated


def test_one_coordinate_windows_tabulate_the_map_and_wider_ones_cannot():
    """Default ``MAP_KNOTS`` knots for windows of one state coordinate and a map used as is; the
    posterior is the map's at every particle up to the interpolation error; a wider window, or
    one knot, is refused at build time."""
    model, prior, _, _ = _static_problem(3, num=1000)
    windows = local_windows(model.geometry, 0.0)
    # A random map (T's last layer drawn, not zero) as the offline map used as is.
    params = local_ot(windows, num_iterations=1).init(jax.random.PRNGKey(0), prior, model).training.params
    params = params._replace(transport=jax.tree.map(
        lambda leaf: leaf + 0.3 * jax.random.normal(jax.random.PRNGKey(1), leaf.shape), params.transport))
    posteriors = []
    for knots in (None, 0):
        update = local_ot(windows, num_iterations=0, initial_map=params, map_knots=knots)
        assert update.apply.func.keywords["structure"].map_knots == (128 if knots is None else 0)
        state = update.init(jax.random.PRNGKey(2), prior, model)
        _, state, _ = update.apply(jax.random.PRNGKey(3), state, prior, jnp.ones(3), model)
        # The map itself (apply may fall back: a random map throws particles far).
        posteriors.append(np.asarray(update.transport(state, prior, jnp.ones(3), model)))
    difference = np.abs(posteriors[0] - posteriors[1]) / np.std(posteriors[1], axis=0)
    # At most L h / 2: knot step h = (about 6 prior stds) / 127, T's slope L about the ratio of
    # the spreads, 2.3: 0.05 / 2 of the map's spread. Most particles sit between kinks: exact.
    # (16 knots: median 0.007, max 0.05.)
    assert np.median(difference) < 1e-3
    assert difference.max() < 0.03
    trained = local_ot(windows, num_iterations=(64, 16), initial_map=params)  # a map that changes: not by default
    assert trained.apply.func.keywords["structure"].map_knots == 0
    assert local_ot(windows, num_iterations=(64, 16), map_knots=32).apply.func.keywords["structure"].map_knots == 32
    wide = local_windows(otf.models.lorenz96(dim=8).geometry, 2.0, 1.0)
    assert local_ot(wide).apply.func.keywords["structure"].map_knots == 0
    with pytest.raises(ValueError, match="map_knots tabulates a map of one state coordinate"):
        local_ot(wide, map_knots=64)
    with pytest.raises(ValueError, match="map_knots must be 0"):
        local_ot(windows, map_knots=1)


def test_local_ot_runs_in_a_filter_with_missing_observations_without_retracing():
    model = otf.models.lorenz96(dim=12, observed=np.arange(0, 12, 2))
    update = local_ot(local_windows(model.geometry, 2.0, 1.0), num_iterations=(64, 16))
    key = jax.random.PRNGKey(0)
    states, observations = otf.simulate(key, model, 20)
    observations = observations.at[3, 1].set(jnp.nan).at[5].set(jnp.nan)
    first = otf.run_filter(key, model, update, observations, 30)
    again = otf.run_filter(key, model, update, observations, 30)
    np.testing.assert_array_equal(first.mean, again.mean)
    assert np.all(np.isfinite(np.asarray(first.mean)))
    transported = update.transport  # the map of the last update serves another observation
    assert callable(transported)


def test_sliced_wasserstein_of_a_translation():
    # theta.(x + v) - theta.x = theta.v for every sample, so SW2^2 = E (theta.v)^2 = |v|^2 / n
    # up to the projections' Monte-Carlo error (std of (theta.v)^2 / |v|^2 is about sqrt(2) / n).
    n, projections = 4, 4096
    x = jax.random.normal(jax.random.PRNGKey(0), (500, n))
    v = jnp.array([3.0, -1.0, 0.0, 2.0])
    value = metrics.sliced_wasserstein(jax.random.PRNGKey(1), x, x + v, num_projections=projections)
    expected = float(jnp.linalg.norm(v)) / np.sqrt(n)
    assert abs(float(value) ** 2 - expected**2) < 4 * np.sqrt(2) / n * expected**2 / np.sqrt(projections)
    # Weights: duplicating every sample with half weight changes nothing.
    doubled = jnp.concatenate([x, x])
    same = metrics.sliced_wasserstein(jax.random.PRNGKey(1), doubled, x + v, jnp.full(1000, 0.5),
                                      num_projections=projections, num_levels=1000)
    np.testing.assert_allclose(same, value, rtol=1e-5)


def test_per_coordinate_w1_sees_a_lost_mode_in_one_coordinate_out_of_fifty():
    dim, num = 50, 1000
    _, _, grid, masses = _static_problem(dim)
    key = jax.random.PRNGKey(0)
    exact = metrics.product_grid_sample(jax.random.PRNGKey(1), grid, masses, num)
    lost = exact.at[:, 7].set(jnp.abs(exact[:, 7]))  # coordinate 7 keeps one mode only
    good = metrics.compare_to_product_grid(key, exact, None, grid, masses, num)
    bad = metrics.compare_to_product_grid(key, lost, None, grid, masses, num)
    assert float(good.w1.max()) < 0.15  # the floor's worst coordinate at N = 1000
    assert float(bad.w1[7]) > 1.0  # half the mass moved by about 2 sqrt(2)
    # The published metric (standardised, bandwidth 4) barely moves: why it cannot be the only one.
    reference = metrics.product_grid_sample(jax.random.PRNGKey(2), grid, masses, num)
    mmd_good = float(metrics.mmd(exact, reference, 4.0 * jnp.std(reference, axis=0).mean()))
    mmd_bad = float(metrics.mmd(lost, reference, 4.0 * jnp.std(reference, axis=0).mean()))
    assert mmd_bad - mmd_good < 0.05


@pytest.mark.long
def test_local_ot_reaches_twice_the_floor_on_the_static_example_at_n_10():
    dim = 10
    model, prior, grid, masses = _static_problem(dim)
    update = local_ot(local_windows(model.geometry, 0.0))
    state = update.init(jax.random.PRNGKey(0), prior, model)
    posterior, _, info = update.apply(jax.random.PRNGKey(1), state, prior, jnp.ones(dim), model)
    found = metrics.compare_to_product_grid(jax.random.PRNGKey(2), posterior, None, grid, masses)
    floor = metrics.compare_to_product_grid(
        jax.random.PRNGKey(2), metrics.product_grid_sample(jax.random.PRNGKey(3), grid, masses, 1000),
        None, grid, masses)
    assert not bool(info.diverged)
    assert float(found.w1.mean()) <= 2.0 * float(floor.w1.mean())
    assert np.all(np.abs(np.mean(np.asarray(posterior) > 0, axis=0) - 0.5) < 0.1)  # both modes everywhere


@pytest.mark.parametrize("state_radius, taper", [(0.0, "step"), (1.0, "step"), (0.0, "gaspari_cohn")])
def test_the_deterministic_layer_is_the_letkf_of_the_windows(x64, state_radius, taper):
    """The layer alone (the fallback) at the actual observation: the LETKF with the same taper
    (a step of the windows' radius, or Gaspari-Cohn with that support) and inflation, missing
    components included."""
    model = otf.models.lorenz96(dim=12, observed=np.arange(0, 12, 2))
    prior = 3.0 + 2.0 * jax.random.normal(jax.random.PRNGKey(0), (40, 12))
    observation = jax.vmap(model.observation_function)(prior[:1])[0] + 0.5
    observation = observation.at[2].set(jnp.nan)
    radius = 2.5 if taper == "step" else 4.5
    update = local_ot(local_windows(model.geometry, radius, state_radius), num_iterations=20,
                      enkf_layer="deterministic", taper=taper, inflation=1.1, divergence_threshold=1e-9)
    state = update.init(jax.random.PRNGKey(1), prior, model)
    posterior, state, info = update.apply(jax.random.PRNGKey(2), state, prior, observation, model)
    assert bool(info.diverged)  # forced: the layer alone
    length_scale = radius if taper == "step" else radius / taper_support(1.0, taper)
    letkf = otf.letkf(otf.localisation(model.geometry, length_scale, taper=taper), inflation=1.1)
    expected, _, _ = letkf.apply(jax.random.PRNGKey(3), letkf.init(jax.random.PRNGKey(3), prior, model),
                                 prior, observation, model)
    np.testing.assert_allclose(posterior, expected, rtol=1e-8, atol=1e-8)
    if taper == "gaspari_cohn":  # and differs from the step taper's
        step = local_ot(local_windows(model.geometry, radius, state_radius), num_iterations=20,
                        enkf_layer="deterministic", inflation=1.1, divergence_threshold=1e-9)
        hard, _, _ = step.apply(jax.random.PRNGKey(2), step.init(jax.random.PRNGKey(1), prior, model), prior,
                                observation, model)
        assert float(jnp.max(jnp.abs(hard - posterior))) > 1e-2


def test_the_deterministic_layer_needs_gaussian_observation_noise():
    model, prior, _, _ = _static_problem(3, num=50)
    update = local_ot(local_windows(model.geometry, 0.0), num_iterations=2, enkf_layer="deterministic")
    state = update.init(jax.random.PRNGKey(0), prior, model)
    with pytest.raises(ValueError, match="additive Gaussian"):
        update.apply(jax.random.PRNGKey(1), state, prior, jnp.ones(3), model._replace(observation_function=None))
    fresh = local_ot(local_windows(model.geometry, 0.0), num_iterations=2, fresh_observations=True)
    with pytest.raises(ValueError, match=r"fresh_observations=True\) needs a model with additive Gaussian"):
        fresh.apply(jax.random.PRNGKey(1), fresh.init(jax.random.PRNGKey(0), prior, model), prior, jnp.ones(3),
                    model._replace(observation_noise_cov=None))
    with pytest.raises(ValueError, match="enkf_layer must be"):
        local_ot(local_windows(model.geometry, 0.0), enkf_layer="square-root")
    with pytest.raises(ValueError, match="taper must be one of"):
        local_ot(local_windows(model.geometry, 0.0), enkf_layer="deterministic", taper="gauss")
    with pytest.raises(ValueError, match="deterministic layer"):
        local_ot(local_windows(model.geometry, 0.0), enkf_layer=True, taper="gaspari_cohn")
    # the local map's sizes are given, never ot()'s rule for n (a window is not the state)
    with pytest.raises(ValueError, match="batch_size"):
        local_ot(local_windows(model.geometry, 0.0), batch_size=None)
    with pytest.raises(ValueError, match="width"):
        local_ot(local_windows(model.geometry, 0.0), width=None)
