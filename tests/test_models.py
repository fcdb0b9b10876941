"""Built-in models: simulation, integrator order, observation consistency, input validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter import models


def test_simulate_shapes_and_key_dependence():
    model = models.lorenz96(dim=10)
    states, observations = otf.simulate(jax.random.key(0), model, 7)
    assert states.shape == (7, 10) and observations.shape == (7, 10)
    other, _ = otf.simulate(jax.random.key(1), model, 7)
    assert not np.allclose(states, other)
    partial = models.lorenz63(observed=(0, 2))
    _, observations = otf.simulate(jax.random.key(0), partial, 3)
    assert observations.shape == (3, 2)


@pytest.mark.parametrize("integrator, order", [("rk4", 4), ("euler", 1)])
def test_integrator_convergence_order(x64, integrator, order):
    x0 = jnp.array([1.0, 2.0, 20.0])

    def flow(dt):
        model = models.lorenz63(dt=dt, integrator=integrator, steps_per_observation=int(round(0.2 / dt)))
        return model.sample_transition(jax.random.key(0), x0)

    reference = flow(1e-4) if integrator == "euler" else flow(5e-4)
    coarse, fine = flow(0.004), flow(0.002)
    ratio = np.linalg.norm(coarse - reference) / np.linalg.norm(fine - reference)
    assert abs(np.log2(ratio) - order) < 0.3


def test_squared_observation_examples():
    static = models.squared_observation(dim=2, noise=0.4, observation_scale=0.5, static=True)
    x = jnp.array([1.0, -2.0])
    np.testing.assert_array_equal(static.sample_transition(jax.random.key(0), x), x)
    np.testing.assert_allclose(static.observation_function(x), [0.5, 2.0])
    keys = jax.random.split(jax.random.key(1), 20_000)
    draws = jax.vmap(static.sample_observation, (0, None))(keys, x)
    np.testing.assert_allclose(draws.mean(0), [0.5, 2.0], atol=0.02)
    np.testing.assert_allclose(draws.std(0), [0.4, 0.4], atol=0.02)
    # log-likelihood is the density of that noise: symmetric in x (the two modes).
    y = jnp.array([0.5, 2.0])
    np.testing.assert_allclose(static.log_likelihood(y, x), static.log_likelihood(y, -x))
    dynamic = models.squared_observation(dim=3)
    moved = jax.vmap(dynamic.sample_transition, (0, None))(keys, jnp.ones(3))
    np.testing.assert_allclose(moved.mean(0), 0.9, atol=0.02)
    np.testing.assert_allclose(moved.std(0), 2 * np.sqrt(0.1), atol=0.02)


def test_model_builders_reject_bad_input():
    with pytest.raises(ValueError, match="integrator"):
        models.lorenz63(integrator="leapfrog")
    with pytest.raises(ValueError, match="observed"):
        models.lorenz63(observed=(0, 3))
    with pytest.raises(ValueError, match="observation_noise_std"):
        models.lorenz63(observation_noise_std=-1.0)
    with pytest.raises(ValueError, match="process_noise_std"):
        models.lorenz96(process_noise_std=-0.1)
    with pytest.raises(ValueError, match="dt"):
        models.lorenz96(dt=0.0)
    with pytest.raises(ValueError, match="steps_per_observation"):
        models.lorenz63(steps_per_observation=0)
    with pytest.raises(ValueError, match="dim"):
        models.squared_observation(dim=0)
    with pytest.raises(ValueError, match="noise"):
        models.squared_observation(noise=-1.0)
    with pytest.raises(ValueError, match="observation_scale"):
        models.squared_observation(observation_scale=0.0)
    model = models.lorenz63()
    for bad in (np.diag([1.0, 0.0, 1.0]), -np.eye(3), np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]])):
        with pytest.raises(ValueError, match="observation_noise_cov"):
            otf.run_filter(jax.random.key(0), model._replace(observation_noise_cov=bad), otf.enkf(),
                           np.zeros((2, 3)), 10)
    eye = np.eye(2)
    with pytest.raises(ValueError, match="R"):
        models.linear_gaussian(eye, eye, eye, -eye, np.zeros(2), eye)
    with pytest.raises(ValueError, match="H"):
        models.linear_gaussian(eye, eye, np.eye(3), eye, np.zeros(2), eye)
    with pytest.raises(ValueError, match="num_steps"):
        otf.simulate(jax.random.key(0), models.lorenz63(), 0)


def test_lorenz_observation_operators_observe_what_they_name():
    """'linear', 'square' and 'abs' apply x, x^2 and |x| to the observed components only, and
    an unknown operator is refused with the names it could have been."""
    x = jnp.array([-2.0, -0.5, 0.0, 1.5, 3.0])
    observed = (4, 0, 1)
    expected = {"linear": [3.0, -2.0, -0.5], "square": [9.0, 4.0, 0.25], "abs": [3.0, 2.0, 0.5]}
    for operator, values in expected.items():
        model = models.lorenz96(dim=5, observed=observed, observation_operator=operator)
        np.testing.assert_allclose(model.observation_function(x), values, rtol=1e-6)
        assert otf.model.model_dimensions(model) == (5, len(observed))
    with pytest.raises(ValueError, match="observation_operator.*'abs'"):
        models.lorenz96(observation_operator="cube")


def test_lorenz96_vector_field_matches_its_definition():
    x = jax.random.normal(jax.random.key(0), (3, 7))  # batched: a leading axis of members
    got = np.asarray(otf.models.lorenz.lorenz96_vector_field(x, 8.0))
    x = np.asarray(x)
    n = x.shape[-1]
    expected = np.array([[(x[b, (i + 1) % n] - x[b, i - 2]) * x[b, i - 1] - x[b, i] + 8.0
                          for i in range(n)] for b in range(3)])
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-5)


def test_simulate_observations_draws_h_plus_the_noise_of_r():
    """Additive Gaussian noise: h(X^i) + N(0, R) (a full R: mean and covariance within 5
    Monte-Carlo standard deviations), prefix-consistent in N; without R the model's sampler
    with a key per particle, exactly."""
    R = np.array([[1.0, 0.6, 0.0], [0.6, 2.0, -0.5], [0.0, -0.5, 0.5]])
    H = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, -1.0]])
    model = models.linear_gaussian(np.eye(2), np.eye(2), H, R, np.zeros(2), np.eye(2))
    num = 20_000
    x = jnp.broadcast_to(jnp.array([0.5, -1.0]), (num, 2))
    y = otf.simulate_observations(jax.random.key(0), model, x)
    noise = np.asarray(y) - np.asarray(x[0]) @ H.T
    mean_sd = np.sqrt(np.diag(R) / num)
    np.testing.assert_array_less(np.abs(noise.mean(0)), 5 * mean_sd)
    cov_sd = np.sqrt((np.outer(np.diag(R), np.diag(R)) + R**2) / num)
    np.testing.assert_array_less(np.abs(np.cov(noise.T) - R), 5 * cov_sd)
    np.testing.assert_array_equal(otf.simulate_observations(jax.random.key(0), model, x[:100]), y[:100])
    sampler_only = model._replace(observation_function=None, observation_noise_cov=None)
    x = jax.random.normal(jax.random.key(1), (7, 2))
    np.testing.assert_array_equal(
        otf.simulate_observations(jax.random.key(2), sampler_only, x),
        jax.vmap(model.sample_observation)(jax.random.split(jax.random.key(2), 7), x))
