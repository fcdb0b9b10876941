"""The OT filter (warm-started OT updates inside ``run_filter``) and the dynamic-example harness."""

import json

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import ot_filter as otf
from ot_filter.experiments.dynamic_example import plot_dynamic_example, run_dynamic_example
from ot_filter.lib.weights import uniform_log_weights

from conftest import perturbed_enkf_reference

DYNAMIC = otf.models.squared_observation(dim=2)


@pytest.mark.long
def test_a_diverging_training_falls_back_and_the_filter_completes():
    # An absurd f learning rate makes every step's training blow up (J overflows to inf/NaN).
    _, observations = otf.simulate(jax.random.key(0), DYNAMIC, 6)
    update = otf.ot(num_iterations=(40, 20), potential_optimizer=optax.sgd(1e30), concavity_points=32)
    result = otf.run_filter(jax.random.key(1), DYNAMIC, update, observations, num_particles=128)
    assert np.all(np.asarray(result.info.diverged))
    chex.assert_tree_all_finite((result.mean, result.particles))
    # info never holds NaN (+inf marks a non-finite loss); the carried networks are healthy.
    for leaf in jax.tree.leaves(result.info):
        assert not np.any(np.isnan(np.asarray(leaf, dtype=float)))
    chex.assert_tree_all_finite(result.final_state.training)
    # Every step fell back to the EnKF: the spread stays that of an EnKF, no collapse or blow-up.
    enkf_result = otf.run_filter(jax.random.key(1), DYNAMIC, otf.enkf(), observations, num_particles=128)
    ratio = np.asarray(result.spread) / np.asarray(enkf_result.spread)
    assert np.all((ratio > 0.7) & (ratio < 1.4))


@pytest.mark.long
def test_vmapped_simulations_match_single_runs(x64):
    # float64: in float32 Adam's normalised steps amplify the programs' different roundings
    # (3.5e-4 apart after 3 steps with f's rate 3e-4); the same arithmetic agrees to 1e-10.
    _, observations = jax.vmap(lambda k: otf.simulate(k, DYNAMIC, 3))(jax.random.split(jax.random.key(4), 2))
    observations = observations.astype(jnp.float64)
    update = otf.ot(num_iterations=(16, 4), concavity_points=0)
    keys = jax.random.split(jax.random.key(5), 2)
    run = lambda k, y: otf.run_filter(k, DYNAMIC, update, y, num_particles=64, save_every=0).mean  # noqa: E731
    batched = jax.jit(jax.vmap(run))(keys, observations)
    for s in range(2):
        single = run(keys[s], observations[s])
        assert single.dtype == jnp.float64
        np.testing.assert_allclose(batched[s], single, rtol=1e-10, atol=1e-10)


@pytest.mark.long
def test_dynamic_example_harness_writes_numbers_and_figures(tmp_path):
    result = run_dynamic_example(
        jax.random.key(0), num_particles=100, num_steps=12, num_simulations=2,
        ot_options={"num_iterations": (64, 16)}, sir_reference=2000,
    )
    summary = result["metrics"]
    json.dumps(summary)  # JSON-ready
    for name in ("enkf", "sir", "ot"):
        assert len(summary[name]["mmd_over_time"]) == 12 and summary[name]["all_finite"]
        assert 0.0 < summary[name]["mmd_average"]["mean"] < 1.5
    assert summary["reference_mode_imbalance"] < 1e-5 and summary["reference_lost_mass"] < 1e-3
    assert summary["ot"]["diverged_steps"] == 0
    assert summary["sir_reference"]["num_particles"] == 2000
    paths = plot_dynamic_example(result, str(tmp_path))
    assert len(paths) == 2 and all((tmp_path / p.split("/")[-1]).stat().st_size > 10_000 for p in paths)


def test_ot_update_ignores_padding_of_a_masked_particle_axis():
    # 48 active particles out of 64: the padding's values must not change anything active.
    update = otf.ot(num_iterations=40, concavity_points=16, enkf_layer=True)
    active = jnp.arange(64) < 48
    base = jax.random.normal(jax.random.key(6), (64, 2))
    y = jnp.array([1.0, 0.3])
    outputs = []
    for fill in (0.0, 1e3):
        particles = jnp.where(active[:, None], base, fill)
        state = update.init(jax.random.key(7), particles, DYNAMIC)
        state = state._replace(log_weights=jnp.where(active, -jnp.log(48.0), -jnp.inf))
        posterior, new_state, info = update.apply(jax.random.key(8), state, particles, y, DYNAMIC)
        assert np.all(np.isneginf(new_state.log_weights[48:]))
        outputs.append((posterior[:48], info.final_loss, info.min_hessian_eigenvalue, new_state.gain))
    chex.assert_trees_all_close(*outputs, rtol=1e-5, atol=1e-5)


@pytest.mark.long
def test_padded_ot_filter_matches_the_unpadded_one():
    # JAX's random streams are prefix-consistent, so k active particles out of N_max reproduce
    # the k-particle filter with the same key (up to rounding in the masked reductions).
    _, observations = otf.simulate(jax.random.key(9), DYNAMIC, 3)
    update = otf.ot(num_iterations=(16, 4), concavity_points=0)
    plain = otf.run_filter(jax.random.key(10), DYNAMIC, update, observations, num_particles=48, save_every=0)
    padded = otf.run_filter(jax.random.key(10), DYNAMIC, update, observations, num_particles=64,
                            save_every=0, num_active=48)
    np.testing.assert_allclose(padded.mean, plain.mean, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(padded.final_particles[:48], plain.final_particles, rtol=1e-3, atol=1e-3)


@pytest.mark.long
def test_an_ensemble_far_from_the_observation_is_caught_by_the_predictive_check():
    # Frozen networks (the identity map) leave the prior N(0, I) in place while y = 50 asks for
    # |x| near 7: the observation is ~35 predictive standard deviations off -> fallback.
    frozen = otf.ot(num_iterations=5, potential_optimizer=optax.sgd(0.0),
                    transport_optimizer=optax.sgd(0.0), prior_smoothing=0.0, concavity_points=0)
    particles = jax.random.normal(jax.random.key(11), (256, 2))
    state = frozen.init(jax.random.key(12), particles, DYNAMIC)
    key = jax.random.key(13)
    for y, flagged in ((jnp.array([50.0, 1.0]), True), (jnp.array([1.0, 1.0]), False)):
        posterior, _, info = frozen.apply(key, state, particles, y, DYNAMIC)
        assert bool(info.diverged) == flagged
        assert (float(info.predictive_z) > 10.0) == flagged
    # The fallback: the perturbed EnKF with the update's own simulated observations.
    posterior, after, _ = frozen.apply(key, state, particles, jnp.array([50.0, 1.0]), DYNAMIC)
    expected = perturbed_enkf_reference(particles, after.simulated_observations, jnp.array([50.0, 1.0]),
                                        after.standardisation, model=DYNAMIC)
    np.testing.assert_allclose(posterior, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("noise", ["known R", "known dense R", "simulator only"])
def test_the_fallback_reads_the_active_particles_and_the_observed_components_only(noise):
    # As above with 200 of 256 particles active (the padding far off) and the second component
    # of y missing: the fallback's gain comes from the active pairs' observed component, the
    # padding lands at the posterior mean. With R known the gain is Cov(X, h) (Cov(h) + R)^-1,
    # for a model that only simulates its observations the simulated pairs' Cov(X, Y) Cov(Y)^-1.
    # A dense R: the missing component's row and column both leave it (only R[0, 0] counts).
    model = {"known R": DYNAMIC, "simulator only": DYNAMIC._replace(observation_noise_cov=None),
             "known dense R": DYNAMIC._replace(observation_noise_cov=jnp.array([[2.0, 1.2], [1.2, 1.5]]))}[noise]
    assert model.has_gaussian_observation_noise == (noise != "simulator only")
    frozen = otf.ot(num_iterations=5, potential_optimizer=optax.sgd(0.0),
                    transport_optimizer=optax.sgd(0.0), prior_smoothing=0.0, concavity_points=0)
    particles = jax.random.normal(jax.random.key(11), (256, 2)).at[200:].set(40.0)
    active = np.arange(256) < 200
    state = frozen.init(jax.random.key(12), particles, model)
    state = state._replace(log_weights=uniform_log_weights(particles, 200))
    y = jnp.array([50.0, jnp.nan])
    posterior, after, info = frozen.apply(jax.random.key(13), state, particles, y, model)
    assert bool(info.diverged) and float(info.predictive_z) > 10.0
    expected = perturbed_enkf_reference(particles, after.simulated_observations, y, after.standardisation, active,
                                        model=model)
    np.testing.assert_allclose(posterior, expected, rtol=1e-5, atol=1e-5)


def test_rebuilt_experiment_models_share_programs_and_follow_the_float_mode():
    # No cache of model objects: a rebuilt model is equal as static structure (compiled programs
    # are reused), and a float64 run gets a float64 model.
    from ot_filter.experiments.dynamic_example import dynamic_model
    from ot_filter.experiments.lorenz63 import lorenz63_models

    assert jax.tree.structure(dynamic_model(2)) == jax.tree.structure(dynamic_model(2))
    assert jax.tree.structure(lorenz63_models()) == jax.tree.structure(lorenz63_models())
    assert dynamic_model(2).observation_noise_cov.dtype == jnp.float32
    with jax.enable_x64(True):
        assert dynamic_model(2).observation_noise_cov.dtype == jnp.float64
        assert lorenz63_models()[1].observation_noise_cov.dtype == jnp.float64
    assert lorenz63_models()[1].observation_noise_cov.dtype == jnp.float32
