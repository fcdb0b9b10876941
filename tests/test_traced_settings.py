"""Numbers traced, structure static: a sweep over an update's numbers is one compiled program
whose results match separate runs, and new numbers or rebuilt objects never recompile."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter import continuous as ct
from ot_filter.filtering import _run_filter


@pytest.fixture(scope="module")
def lorenz63_data():
    model = otf.models.lorenz63()
    _, observations = otf.simulate(jax.random.key(0), model, 40)
    return model, observations


def _sweep_matches_separate_runs(model, observations, build, values, num_particles):
    key = jax.random.key(1)

    def mean(value):
        return otf.run_filter(key, model, build(value), observations, num_particles, save_every=0).mean

    swept = np.asarray(jax.jit(jax.vmap(mean))(jnp.asarray(values)))
    # The same program, one value at a time: equal up to float32 rounding.
    one_at_a_time = np.stack([np.asarray(jax.jit(mean)(value)) for value in values])
    # (batched and unbatched kernels round differently; chaos grows it: the first 20 cycles)
    np.testing.assert_allclose(swept[:, :20], one_at_a_time[:, :20], rtol=1e-4, atol=1e-4)
    # Built from a Python number (concrete): the same filter; rounding differences (a traced vs a
    # folded constant) grow over the chaotic cycles, so compare the first ten.
    concrete = np.stack([np.asarray(mean(value)) for value in values])
    np.testing.assert_allclose(swept[:, :10], concrete[:, :10], rtol=1e-3, atol=1e-3)
    assert not np.allclose(concrete[0], concrete[-1])  # the number does reach the update


@pytest.mark.parametrize("perturbed", [True, False])
@pytest.mark.long
def test_enkf_inflation_sweep_is_one_program_matching_separate_runs(lorenz63_data, perturbed):
    model, observations = lorenz63_data
    _sweep_matches_separate_runs(
        model, observations, lambda a: otf.enkf(inflation=a, perturbed=perturbed, rotate=not perturbed),
        [1.0, 1.05, 1.2], 10,
    )


@pytest.mark.long
def test_sir_jitter_sweep_matches_separate_runs(lorenz63_data):
    model, observations = lorenz63_data
    _sweep_matches_separate_runs(
        model, observations, lambda j: otf.sir(ess_threshold=0.5, jitter=j), [0.0, 0.5, 0.9], 100
    )


@pytest.mark.long
def test_ot_learning_rate_sweep_matches_separate_runs():
    model = otf.models.squared_observation(dim=1, noise=0.4, observation_scale=0.5, static=True)
    observations = jnp.ones((1, 1))
    key = jax.random.key(3)

    def mean(rate):
        update = otf.ot(num_iterations=30, batch_size=32, concavity_points=0, transport_learning_rate=rate)
        return otf.run_filter(key, model, update, observations, 64, save_every=0).mean

    rates = [1e-4, 1e-3, 1e-2]
    swept = jax.jit(jax.vmap(mean))(jnp.asarray(rates))
    separate = np.stack([np.asarray(mean(rate)) for rate in rates])
    np.testing.assert_allclose(swept, separate, rtol=1e-4, atol=1e-5)
    assert not np.allclose(separate[0], separate[-1])


@pytest.mark.long
def test_kernel_gain_epsilon_sweep_matches_separate_runs():
    model = ct.ornstein_uhlenbeck()
    dt = 0.01
    increments = ct.simulate_sde(jax.random.key(0), model, dt, 20).increments
    key = jax.random.key(2)

    def mean(epsilon):
        return ct.run_fpf(key, model, ct.kernel_gain(epsilon=epsilon), increments, dt, 50).mean

    epsilons = [0.05, 0.2, 1.0]
    swept = jax.jit(jax.vmap(mean))(jnp.asarray(epsilons))
    separate = np.stack([np.asarray(mean(epsilon)) for epsilon in epsilons])
    np.testing.assert_allclose(swept, separate, rtol=1e-4, atol=1e-5)


@pytest.mark.long
def test_new_numbers_and_rebuilt_objects_do_not_recompile(lorenz63_data):
    _, observations = lorenz63_data
    key = jax.random.key(0)
    otf.run_filter(key, otf.models.lorenz63(), otf.enkf(inflation=1.01), observations, 10)
    before = _run_filter._cache_size()
    for inflation in (1.02, 1.07, jnp.float32(1.1)):
        # a new model object and a new update each time: equal structure, new numbers
        otf.run_filter(key, otf.models.lorenz63(rho=28.5), otf.enkf(inflation=inflation), observations, 10)
    assert _run_filter._cache_size() == before
    otf.run_filter(key, otf.models.lorenz63(), otf.enkf(inflation=1.01, perturbed=False), observations, 10)
    assert _run_filter._cache_size() == before + 1  # new structure: one new program


def test_concrete_numbers_are_checked_and_traced_ones_pass():
    with pytest.raises(ValueError, match="inflation must be >= 1"):
        otf.enkf(inflation=0.9)
    with pytest.raises(ValueError, match="jitter must be >= 0"):
        otf.sir(jitter=-1.0)
    with pytest.raises(ValueError, match="ess_threshold must be"):
        otf.sir(ess_threshold=1.5)
    with pytest.raises(ValueError, match="transport_learning_rate must be > 0"):
        otf.ot(transport_learning_rate=0.0)
    with pytest.raises(ValueError, match="batch_size must be an int >= 2"):
        otf.ot(batch_size=1)
    with pytest.raises(ValueError, match="epsilon must be > 0"):
        ct.kernel_gain(epsilon=0.0)
    jax.vmap(lambda a: jax.tree.leaves(otf.enkf(inflation=a)))(jnp.ones(2))


def test_bad_inputs_are_refused_by_name(lorenz63_data):
    model, observations = lorenz63_data
    with pytest.raises(ValueError, match="initial_particles must be finite"):
        otf.run_filter(jax.random.key(0), model, otf.enkf(), observations, 4,
                       initial_particles=jnp.full((4, 3), jnp.nan))
    with pytest.raises(ValueError, match="estimate and truth must broadcast"):
        otf.metrics.rmse(jnp.zeros((5, 3)), jnp.zeros((4, 3)))
    with pytest.raises(TypeError, match="log_weights"):
        otf.run_filter(jax.random.key(0), model, otf.BayesUpdate(lambda k, x, m: (), lambda *a: a),
                       observations, 4)
