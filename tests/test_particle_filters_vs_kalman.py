"""EnKF and SIR with N = 10^5 particles against the exact Kalman filter (linear-Gaussian model).

Filter particles are not independent posterior samples (the EnKF gain and SIR's weights are
estimated from the ensemble itself and errors propagate in time), so the Monte-Carlo error is
measured, not assumed: R = 32 independent replications (one vmapped program) give, for every
time step and entry, the mean over replications and its standard error s / sqrt(R).

- Consistency: |average - exact| < 5 s / sqrt(R) (t-test, 31 degrees of freedom).
- Accuracy scale: s < 4 sqrt(P_ii / N_eff), i.e. the error is the O(1 / sqrt(N)) Monte-Carlo
  error of N_eff = N samples (N_eff = ESS for SIR), not something larger.
- SIR's marginal log-likelihood: unbiased for the likelihood, so log Z_hat has bias -Var/2;
  the delta method gives Var ~ sum_t (1/ESS_t - 1/N).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from conftest import random_linear_gaussian

NUM_PARTICLES = 100_000
NUM_STEPS = 5
NUM_REPLICATIONS = 32


@pytest.fixture(scope="module")
def problem():
    model = otf.models.linear_gaussian(*random_linear_gaussian(11))
    _, observations = otf.simulate(jax.random.key(11), model, NUM_STEPS)
    return model, observations, otf.kalman_filter(model, observations)


def replicate(model, update, observations):
    """Means [R, T, n], covariances [R, T, n, n] and info of R independent filter runs."""

    def one_run(key):
        result = otf.run_filter(key, model, update, observations, NUM_PARTICLES)
        weights = jnp.exp(result.log_weights)
        anomalies = result.particles - result.mean[:, None, :]
        cov = jnp.einsum("tk,tki,tkj->tij", weights, anomalies, anomalies)
        return result.mean, cov, result.info

    keys = jax.random.split(jax.random.key(0), NUM_REPLICATIONS)
    means, covs, info = jax.jit(jax.vmap(one_run))(keys)
    return np.asarray(means, np.float64), np.asarray(covs, np.float64), info


def assert_consistent(estimates, exact, scale_bound=None):
    standard_error = estimates.std(axis=0, ddof=1) / np.sqrt(NUM_REPLICATIONS)
    error = np.abs(estimates.mean(axis=0) - np.asarray(exact, np.float64))
    np.testing.assert_array_less(error, 5 * standard_error + 1e-7)
    if scale_bound is not None:
        np.testing.assert_array_less(estimates.std(axis=0, ddof=1), scale_bound)


@pytest.mark.parametrize(
    "update",
    [otf.enkf(), otf.enkf(perturbed=False)],
    ids=["perturbed", "square_root"],
)
@pytest.mark.long
def test_enkf_matches_kalman(problem, update):
    model, observations, exact = problem
    means, covs, _ = replicate(model, update, observations)
    variance = np.diagonal(np.asarray(exact.cov), axis1=1, axis2=2)
    assert_consistent(means, exact.mean, 4 * np.sqrt(variance / NUM_PARTICLES))
    assert_consistent(covs, exact.cov)


@pytest.mark.long
def test_simulation_based_enkf_matches_kalman(problem):
    """Without h and R the gain Cov(X, Y) Cov(Y)^-1 comes from simulated pairs only."""
    model, observations, exact = problem
    simulator_only = model._replace(observation_function=None, observation_noise_cov=None)
    means, covs, _ = replicate(simulator_only, otf.enkf(), observations)
    variance = np.diagonal(np.asarray(exact.cov), axis1=1, axis2=2)
    assert_consistent(means, exact.mean, 4 * np.sqrt(variance / NUM_PARTICLES))
    assert_consistent(covs, exact.cov)


@pytest.mark.parametrize("resampling", ["systematic", *(pytest.param(s, marks=pytest.mark.long)
                                                      for s in ("multinomial", "stratified", "residual"))])
def test_sir_matches_kalman_with_marginal_likelihood(problem, resampling):
    model, observations, exact = problem
    means, covs, info = replicate(model, otf.sir(resampling=resampling), observations)
    ess = np.asarray(info.ess, np.float64)  # [R, T]
    variance = np.diagonal(np.asarray(exact.cov), axis1=1, axis2=2)
    assert_consistent(means, exact.mean, 4 * np.sqrt(variance / ess.min(axis=0)[:, None]))
    assert_consistent(covs, exact.cov)

    log_likelihoods = np.asarray(info.log_likelihood_increment, np.float64).sum(axis=1)
    delta_variance = np.sum(1.0 / ess - 1.0 / NUM_PARTICLES, axis=1).mean()
    debiased = log_likelihoods + delta_variance / 2
    assert_consistent(debiased, exact.log_likelihood)
    # The spread across replications is what the delta method predicts (within a factor 2).
    assert 0.5 < log_likelihoods.std(ddof=1) / np.sqrt(delta_variance) < 2.0
