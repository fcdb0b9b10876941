"""The local ensemble transform Kalman filter (LETKF; Hunt, Kostelich & Szunyogh 2007).

Each state coordinate j is analysed on its own with the observations near it, their inverse
error variances multiplied by the taper rho_jk of their distance (observation-error, or R,
localisation). With the prior anomalies A (inflated), the whitened observation anomalies
S = (h(X^i) - mean h) L^{-1} / sqrt(k - 1) and innovation d = L^{-1} (y - mean h), coordinate j
takes the ETKF transform (``lib.transform``) of

    S_j = S[:, K_j] diag(sqrt(rho_j)),   d_j = sqrt(rho_j) * d[K_j]

(K_j its neighbouring observations, ``localisation.Localisation``):

    mean_j <- mean_j + w_j^T A[:, j] / sqrt(k - 1),   A[:, j] <- T_j A[:, j].

The local analyses are independent, so they are one ``vmap`` over the n coordinates (or
``lax.map`` over batches of them, ``batch_size``, to bound memory): O(n N^2 min(N, K)) work
and O(n N K) memory per update, linear in n. A missing component (NaN in y) gets weight 0 in
every local analysis, exactly as if it were deleted (with a diagonal R; with a correlated R the
whitening mixes components, and as DAPPER does the taper applies to the whitened ones).

Inflation multiplies the prior anomalies (as in ``enkf``); ``rotate=True`` applies one random
mean-preserving rotation to the posterior anomalies after all the local analyses (as
``enkf``'s). Padding particles (``updates.base``) are zero anomaly rows: every local analysis
is the k-particle one.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import masked_mean_and_anomalies
from ot_filter.lib.static import bind
from ot_filter.lib.transform import etkf_transform
from ot_filter.lib.validation import check_int, check_number
from ot_filter.lib.weights import active_first, active_mask, count_active
from ot_filter.localisation import Localisation, check_localisation, check_localised_analysis
from ot_filter.model import StateSpaceModel
from ot_filter.updates.base import BayesUpdate, UniformWeightsState, uniform_weights_init
from ot_filter.updates.enkf import MAX_ROTATED_PARTICLES, random_rotation, whitened_observations

Array = jax.Array

__all__ = ["LETKFInfo", "LETKFSettings", "letkf", "letkf_apply"]


class LETKFSettings(NamedTuple):
    """The LETKF's numbers (traced: a vmap over inflation and radius is one program)."""

    inflation: Array  # multiplicative inflation (>= 1) of the prior anomalies
    localisation: Localisation  # taper, radius (traced) and neighbour lists


class LETKFInfo(NamedTuple):
    innovation_condition: Array  # max over coordinates of the local 1 + max eigenvalue of S_j S_j^T
    local_observations: Array  # mean over coordinates of the sum of the taper weights used


def letkf(localisation: Localisation, inflation: float = 1.0, rotate: bool = False,
          batch_size: int | None = None) -> BayesUpdate:
    """Builds the LETKF Bayes update (needs a model with additive Gaussian noise, h and R).

    Args:
      localisation: ``ot_filter.localisation(model.geometry, radius, taper)``; its radius may be
        traced.
      inflation: multiplicative inflation (>= 1) of the prior anomalies; may be traced.
      rotate: random mean-preserving rotation of the posterior anomalies (DAPPER's ``rot``;
        N <= 4096). Static.
      batch_size: analyse this many coordinates at a time (``lax.map``) instead of all at once;
        bounds the memory at O(batch_size N K). Static.
    """
    check_localisation(localisation)
    if batch_size is not None:
        batch_size = check_int("batch_size", batch_size, minimum=1)
    settings = LETKFSettings(check_number("inflation", inflation, minimum=1.0), localisation)
    return BayesUpdate(uniform_weights_init,
                       bind(letkf_apply, settings, rotate=bool(rotate), batch_size=batch_size))


def letkf_apply(settings: LETKFSettings, key: Array, state: UniformWeightsState, particles: Array,
                observation: Array, model: StateSpaceModel, *, rotate: bool,
                batch_size: int | None):
    """One LETKF analysis (``letkf``'s ``apply`` with its settings and structure given)."""
    num_particles, n = particles.shape
    m = observation.shape[0]
    localisation = settings.localisation
    check_localised_analysis("letkf", localisation, model, n, m)
    if rotate and num_particles > MAX_ROTATED_PARTICLES:
        raise ValueError(f"letkf(rotate=True) needs num_particles <= {MAX_ROTATED_PARTICLES}")
    dtype = particles.dtype
    active = active_mask(state.log_weights)
    num_active = count_active(state.log_weights)
    mean, anomalies = masked_mean_and_anomalies(particles, active, num_active)
    anomalies = settings.inflation * anomalies
    observed = jnp.isfinite(observation)
    whitened, innovation, over_scale = whitened_observations(  # S [N, m], d [m]
        mean, anomalies, observation, model, active, num_active)
    weights = localisation.weights().astype(dtype) * observed[localisation.neighbours]  # [n, K]

    def analyse(inputs):
        neighbours, weight, column = inputs  # [K], [K], [N]
        root = jnp.sqrt(weight)
        mean_weights, posterior, s2 = etkf_transform(
            whitened[:, neighbours] * root, innovation[neighbours] * root, column[:, None]
        )
        return over_scale(mean_weights @ column), posterior[:, 0], 1.0 + jnp.max(s2)

    inputs = (localisation.neighbours, weights, anomalies.T)
    if batch_size is None:
        increments, posterior_anomalies, conditions = jax.vmap(analyse)(inputs)
    else:
        increments, posterior_anomalies, conditions = jax.lax.map(analyse, inputs,
                                                                  batch_size=batch_size)
    posterior_anomalies = posterior_anomalies.T  # [N, n]
    posterior_mean = mean + increments
    if rotate:
        order = active_first(active)
        rotated = random_rotation(key, posterior_anomalies[order], num_active)
        posterior_anomalies = jnp.zeros_like(rotated).at[order].set(rotated)
    particles = posterior_mean + posterior_anomalies
    particles = jnp.where(active[:, None], particles, posterior_mean)
    info = LETKFInfo(jnp.max(conditions), jnp.mean(jnp.sum(weights, axis=1)))
    return particles, state, info
