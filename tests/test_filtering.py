"""run_filter: storage options, jit/no-jit and vmap equivalence, no retracing, missing data, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from conftest import random_linear_gaussian


@pytest.fixture(scope="module")
def setup():
    model = otf.models.linear_gaussian(*random_linear_gaussian(5))
    states, observations = otf.simulate(jax.random.key(5), model, 10)
    return model, states, observations


@pytest.mark.parametrize("update", [otf.sir(), otf.enkf()], ids=["sir", "enkf"])
@pytest.mark.long
def test_save_every_changes_storage_not_results(setup, update):
    model, _, observations = setup
    full = otf.run_filter(jax.random.key(0), model, update, observations, 32, save_every=1)
    assert full.particles.shape == (10, 32, 3) and full.mean.shape == (10, 3)
    every3 = otf.run_filter(jax.random.key(0), model, update, observations, 32, save_every=3)
    np.testing.assert_array_equal(np.asarray(every3.saved_steps), [2, 5, 8])
    np.testing.assert_allclose(every3.particles, full.particles[np.array([2, 5, 8])], rtol=1e-6)
    none = otf.run_filter(jax.random.key(0), model, update, observations, 32, save_every=0)
    assert none.particles is None and none.log_weights is None
    beyond = otf.run_filter(jax.random.key(0), model, update, observations, 32, save_every=11)
    assert beyond.particles is None and beyond.saved_steps.size == 0
    for result in (every3, none):
        np.testing.assert_allclose(result.mean, full.mean, rtol=1e-6)
        np.testing.assert_allclose(result.final_particles, full.particles[-1], rtol=1e-6)


@pytest.mark.long
def test_jit_and_no_jit_agree(setup):
    model, _, observations = setup
    update = otf.sir(resampling="stratified", ess_threshold=0.5, jitter=0.3)
    jitted = otf.run_filter(jax.random.key(1), model, update, observations, 16)
    with jax.disable_jit():
        eager = otf.run_filter(jax.random.key(1), model, update, observations, 16)
    np.testing.assert_allclose(eager.mean, jitted.mean, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(eager.info.resampled, jitted.info.resampled)


@pytest.mark.long
def test_vmap_over_keys_and_observations_matches_single_runs(setup):
    model, _, _ = setup
    keys = jax.random.split(jax.random.key(2), 3)
    _, observations = jax.vmap(lambda k: otf.simulate(k, model, 6))(keys)
    update = otf.enkf(perturbed=False)
    batched = jax.jit(jax.vmap(lambda k, y: otf.run_filter(k, model, update, y, 20).mean))(keys, observations)
    for i in range(3):
        single = otf.run_filter(keys[i], model, update, observations[i], 20).mean
        np.testing.assert_allclose(batched[i], single, rtol=1e-5, atol=1e-6)


def test_no_retracing_for_new_keys_and_observations(setup):
    model, _, observations = setup
    traces = []

    def counting_transition(key, x):
        traces.append(1)  # runs only while tracing
        return model.sample_transition(key, x)

    counted = model._replace(sample_transition=counting_transition)
    update = otf.enkf()
    otf.run_filter(jax.random.key(0), counted, update, observations, 8, save_every=0)
    first = len(traces)
    for seed in (1, 2):
        otf.run_filter(jax.random.key(seed), counted, update, observations + seed, 8, save_every=0)
    assert len(traces) == first


@pytest.mark.parametrize("update", [otf.sir(), otf.enkf()], ids=["sir", "enkf"])
def test_missing_observations_are_skipped(setup, update):
    model, _, observations = setup
    observations = np.array(observations)
    observations[3] = np.nan
    result = otf.run_filter(jax.random.key(3), model, update, observations, 20_000, save_every=1)
    assert np.asarray(result.observed).tolist() == [t != 3 for t in range(10)]
    assert np.all(np.isfinite(result.mean)) and np.all(np.isfinite(result.particles))
    exact = otf.kalman_filter(model, observations)  # also skips t = 3
    # A filter mean's Monte-Carlo error is up to ~3x the iid sqrt(P / N) (measured in
    # test_particle_filters_vs_kalman); allow 6 of those.
    tolerance = 6 * 3 * np.sqrt(np.diagonal(np.asarray(exact.cov), axis1=1, axis2=2) / 20_000)
    np.testing.assert_array_less(np.abs(result.mean - exact.mean), tolerance)


def test_initial_particles_are_used(setup):
    model, _, observations = setup
    start = jnp.full((4, 3), 100.0)
    update = otf.enkf()
    result = otf.run_filter(jax.random.key(0), model, update, observations[:1], 4,
                            initial_particles=start)
    assert np.all(np.abs(result.final_particles) > 10)  # far from the model's own prior


def test_bad_input_is_rejected_before_work(setup):
    model, _, observations = setup
    update = otf.enkf()
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="observations"):
        otf.run_filter(key, model, update, observations[:, :1], 10)
    with pytest.raises(ValueError, match="observations"):
        otf.run_filter(key, model, update, observations[0], 10)
    with pytest.raises(ValueError, match="num_particles"):
        otf.run_filter(key, model, update, observations, 1)
    with pytest.raises(TypeError, match="num_particles"):
        otf.run_filter(key, model, update, observations, 10.0)
    with pytest.raises(TypeError, match="update"):
        otf.run_filter(key, model, lambda *a: a, observations, 10)
    with pytest.raises(ValueError, match="initial_particles"):
        otf.run_filter(key, model, update, observations, 10, initial_particles=jnp.zeros((10, 2)))
    with pytest.raises(ValueError, match="save_every"):
        otf.run_filter(key, model, update, observations, 10, save_every=-1)
    with pytest.raises(ValueError, match="log_likelihood"):
        otf.run_filter(key, model._replace(log_likelihood=None), otf.sir(), observations, 10)
    bad_model = model._replace(sample_transition=lambda key, x: x[:2])
    with pytest.raises(ValueError, match="sample_transition"):
        otf.run_filter(key, bad_model, update, observations, 10)
    with pytest.raises(TypeError, match="StateSpaceModel"):
        otf.run_filter(key, object(), update, observations, 10)


def test_spread_output_is_metrics_spread(setup):
    model, _, observations = setup
    result = otf.run_filter(jax.random.key(4), model, otf.sir(ess_threshold=0.0), observations, 64)
    expected = otf.metrics.spread(result.particles, result.log_weights)
    # Same formula, fused inside the scan vs eager: float32 rounding (1/(1 - sum w^2) amplifies it).
    np.testing.assert_allclose(result.spread, expected, rtol=1e-4)
