"""The localised flow-matching update: local_ot()'s windows and layers with a regression-trained
flow (closed forms and exact references first: the Gaussian posterior, the static example's exact
marginals, the LETKF that the deterministic layer is)."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from conftest import assert_gaussian_posterior
from ot_filter import metrics
from ot_filter.localisation import local_windows
from ot_filter.models import linear_gaussian, squared_observation
from ot_filter.reference import squared_observation_posterior
from ot_filter.updates.local_flow import _tail_safe_flow

KEY = jax.random.PRNGKey


def _static_problem(dim, num=1000, seed=0):
    model = squared_observation(dim=dim, noise=0.4, observation_scale=0.5, static=True)
    prior = jax.vmap(model.sample_initial)(jax.random.split(KEY(seed), num))
    exact = squared_observation_posterior(1.0, 0.4, scale=0.5)
    masses = jnp.broadcast_to(exact.density, (dim,) + exact.density.shape)
    return model, prior, exact.grid, masses


def test_the_static_example_at_n_10_is_within_twice_the_floor_with_both_modes_everywhere():
    """Independent coordinates observed one by one (radius 0): the local problem IS each
    coordinate's Bayes problem. Measured 1.14-1.20 times the floor over three training keys
    (benchmarks/results/local_flow/); the bound is the issue's target."""
    dim = 10
    model, prior, grid, masses = _static_problem(dim)
    update = otf.local_flow(local_windows(model.geometry, 0.0))
    state = update.init(KEY(0), prior, model)
    posterior, state, info = update.apply(KEY(1), state, prior, jnp.ones(dim), model)
    found = metrics.compare_to_product_grid(KEY(2), posterior, None, grid, masses)
    floor = metrics.compare_to_product_grid(KEY(2), metrics.product_grid_sample(KEY(3), grid, masses, 1000), None,
                                            grid, masses)
    assert not bool(info.diverged)
    assert float(found.w1.mean()) <= 2.0 * float(floor.w1.mean())
    assert float(found.w1.max()) <= 2.0 * float(floor.w1.max())  # no coordinate left behind
    assert np.all(np.abs(np.mean(np.asarray(posterior) > 0, axis=0) - 0.5) < 0.1)  # both modes everywhere
    # One-coordinate windows: the flow on the line is increasing, so every coordinate keeps the
    # particles' order (the prior's dependence between coordinates is kept).
    np.testing.assert_array_equal(np.argsort(posterior, axis=0), np.argsort(prior, axis=0))


def test_a_gaussian_posterior_for_two_observations_without_retraining():
    """X ~ N(1, 4), Y = X + N(0, 1): the exact posterior given the particles' moments, at y = 2
    (trained) and y = -1 (``transport``), with the tolerances of ``test_flow_matching`` (the
    identity map is off by 0.9 sd in the mean and 5 times in the variance)."""
    model = linear_gaussian(A=jnp.eye(1), Q=jnp.eye(1), H=jnp.eye(1), R=jnp.eye(1), m0=jnp.ones(1),
                            P0=4 * jnp.eye(1))
    particles = 1.0 + 2.0 * jax.random.normal(KEY(5), (1000, 1))
    update = otf.local_flow(local_windows(otf.ring(1), 0.0))
    state = update.init(KEY(1), particles, model)
    posterior, state, info = update.apply(KEY(2), state, particles, jnp.array([2.0]), model)
    assert not bool(info.diverged)
    assert_gaussian_posterior(update, state, particles, posterior, mean_tol=0.12, var_range=(0.85, 1.12))


def test_the_tails_are_translated_with_the_kth_start():
    """A field v = a x integrates to x e^a (Heun: to second order); the k least and largest
    active starts move as the (k+1)-th does, the rest by the flow. The inactive row (-2) would
    shift the lower bound to -2 if it counted."""
    a, k, steps = 0.5, 2, 64

    class Linear:
        @staticmethod
        def apply(params, x, t, y):
            return params * x

    x = jnp.array([[-9.0], [-3.0], [-1.0], [-2.0], [0.5], [2.0], [7.0], [40.0]])
    active = jnp.ones(8, bool).at[3].set(False)  # an inactive row is not a bound
    moved = _tail_safe_flow(Linear(), a, steps, active, jnp.asarray(k))(x, jnp.zeros((8, 1)))
    flow = np.exp(a) * np.asarray(x[:, 0])  # the flow proper, up to Heun's O(dt^2)
    low, high = -1.0, 2.0  # the (k+1)-th least and largest active starts: -9, -3 | -1 ... 2 | 7, 40
    expected = np.where(x[:, 0] < low, x[:, 0] + (np.exp(a) - 1) * low,
                        np.where(x[:, 0] > high, x[:, 0] + (np.exp(a) - 1) * high, flow))
    np.testing.assert_allclose(moved[:, 0], expected, rtol=1e-4, atol=1e-4)
    whole = _tail_safe_flow(Linear(), a, steps, active, jnp.asarray(0))(x, jnp.zeros((8, 1)))
    np.testing.assert_allclose(whole[active, 0], flow[np.asarray(active)], rtol=1e-4)
    # Two active particles and k = 2: the bounds stay in order (the flow at both).
    two = _tail_safe_flow(Linear(), a, steps, jnp.arange(8) < 2, jnp.asarray(k))(x, jnp.zeros((8, 1)))
    np.testing.assert_allclose(two[:2, 0], flow[:2], rtol=1e-4)


def test_with_the_deterministic_layer_a_linear_gaussian_update_stays_the_letkf():
    """Linear observations of Gaussian particles: the layer (the LETKF of the windows) is already
    the local posterior, so the flow from it should move the particles little. Measured 0.06-0.08
    posterior spreads on average over three prior seeds (fresh observations, the default here;
    0.11-0.18 without them); a flow that ignored the layer would start from the prior, several
    spreads away."""
    model = otf.models.lorenz96(dim=12)
    prior = 3.0 + jax.random.normal(KEY(0), (100, 12)) @ (0.3 * jnp.eye(12) + 0.1)
    observation = jax.vmap(model.observation_function)(prior[:1])[0] + 0.7
    windows = local_windows(model.geometry, 2.0)
    update = otf.local_flow(windows, enkf_layer="deterministic")
    state = update.init(KEY(1), prior, model)
    posterior, state, info = update.apply(KEY(2), state, prior, observation, model)
    assert not bool(info.diverged)
    letkf = otf.letkf(otf.localisation(model.geometry, 2.0, taper="step"))
    expected, _, _ = letkf.apply(KEY(3), letkf.init(KEY(3), prior, model), prior, observation, model)
    spread = np.asarray(expected).std(axis=0)
    assert np.mean(np.abs(np.asarray(posterior - expected)) / spread) < 0.15
    # ... and the layer is what a divergence falls back to, exactly.
    forced = otf.local_flow(windows, enkf_layer="deterministic", divergence_threshold=1e-9)
    fallen, _, info = forced.apply(KEY(2), forced.init(KEY(1), prior, model), prior, observation, model)
    assert bool(info.diverged)
    np.testing.assert_allclose(fallen, expected, rtol=1e-4, atol=1e-4)


def test_divergence_falls_back_to_the_local_enkf_as_local_ot_does():
    """A rate that overflows: the update reports the divergence and returns the local perturbed
    EnKF (the layer alone, the same simulated observations as local_ot's for the same key)."""
    model, prior, _, _ = _static_problem(3, num=200)
    windows = local_windows(model.geometry, 0.0)
    update = otf.local_flow(windows, num_iterations=50, learning_rate=1e6)
    state = update.init(KEY(0), prior, model)
    posterior, state, info = update.apply(KEY(1), state, prior, jnp.ones(3), model)
    assert bool(info.diverged) and bool(state.diverged) and int(state.num_updates) == 0
    assert np.all(np.isfinite(posterior)) and not np.isnan(float(info.final_loss))
    reference = otf.local_ot(windows, num_iterations=20, divergence_threshold=1e-9)
    expected, _, _ = reference.apply(KEY(1), reference.init(KEY(0), prior, model), prior, jnp.ones(3), model)
    np.testing.assert_allclose(posterior, expected, rtol=1e-5, atol=1e-5)


def test_in_a_filter_with_missing_observations_jit_equals_eager_without_retracing():
    model = otf.models.lorenz96(dim=12, observed=np.arange(0, 12, 2))
    update = otf.local_flow(local_windows(model.geometry, 2.0, 1.0), num_iterations=(64, 16), batch_size=64,
                            width=16)
    _, observations = otf.simulate(KEY(0), model, 12)
    observations = observations.at[3, 1].set(jnp.nan).at[5].set(jnp.nan)
    first = otf.run_filter(KEY(1), model, update, observations, 30)
    again = otf.run_filter(KEY(1), model, update, observations, 30)
    np.testing.assert_array_equal(first.mean, again.mean)
    assert np.all(np.isfinite(np.asarray(first.mean)))
    # One step, eager (outside any jit) and jitted, give the same particles; a second call with
    # other numbers of the same shapes does not retrace.
    prior = 3.0 + jax.random.normal(KEY(2), (30, 12))
    state = update.init(KEY(3), prior, model)
    eager, _, _ = update.apply(KEY(4), state, prior, observations[3], model)
    jitted, _, _ = jax.jit(update.apply)(KEY(4), state, prior, observations[3], model)
    np.testing.assert_allclose(eager, jitted, rtol=1e-5, atol=1e-5)
    module = importlib.import_module("ot_filter.updates.local_flow")
    before = module._apply._cache_size()
    update.apply(KEY(5), state, prior + 1.0, observations[4], model)
    assert module._apply._cache_size() == before


def test_the_learning_rate_is_traced_a_vmap_over_it_is_one_program():
    model, prior, _, _ = _static_problem(2, num=200)
    windows = local_windows(model.geometry, 0.0)

    def one(rate):
        update = otf.local_flow(windows, num_iterations=100, batch_size=64, width=16, learning_rate=rate)
        posterior, _, _ = update.apply(KEY(1), update.init(KEY(0), prior, model), prior, jnp.ones(2), model)
        return posterior

    rates = jnp.array([1e-4, 1e-2])
    both = jax.vmap(one)(rates)
    np.testing.assert_allclose(both[1], one(1e-2), rtol=1e-4, atol=1e-4)
    assert float(jnp.max(jnp.abs(both[0] - both[1]))) > 1e-3  # the rate is used


def test_errors_name_the_argument():
    model, prior, _, _ = _static_problem(3, num=50)
    windows = local_windows(model.geometry, 0.0)
    with pytest.raises(TypeError, match="windows must be"):
        otf.local_flow(otf.localisation(model.geometry, 1.0))
    with pytest.raises(ValueError, match="activation"):
        otf.local_flow(windows, activation="swish-ish")
    with pytest.raises(ValueError, match="tail_particles"):
        otf.local_flow(windows, tail_particles=-1)
    update = otf.local_flow(windows, num_iterations=2)
    with pytest.raises(ValueError, match="needs the model"):
        update.init(KEY(0), prior)
    state = update.init(KEY(0), prior, model)
    with pytest.raises(ValueError, match="particles must have shape"):
        update.apply(KEY(1), state, prior[:, :2], jnp.ones(3), model)
    with pytest.raises(ValueError, match=r"and observation \(3,\)"):
        update.transport(state, prior, jnp.ones(2))
    layered = otf.local_flow(windows, num_iterations=2, enkf_layer="deterministic")
    with pytest.raises(ValueError, match="needs the model"):
        layered.transport(layered.init(KEY(0), prior, model), prior, jnp.ones(3))
