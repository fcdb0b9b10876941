"""The localised ensemble transform particle filter (LETPF): each state coordinate moved by the
exact one-dimensional optimal transport to its locally weighted ensemble.

Coordinate j weighs the particles by the observations near it, each log-likelihood term
multiplied by the taper rho_jk of its distance (as the LETKF divides R by it; Poterjoy 2016, Penny
& Miyoshi 2016):

    log w_i^j = sum_k rho_jk log l_k(y_k | X^i),   log l_k = -(1/2) z_ik^2,  z_i = L^{-1} (y - h(X^i))

(whitened components, the LETKF's convention for a correlated R), and its values move by the
optimal coupling between the equally weighted and the weighted ensemble of that coordinate
(``lib.monotone.monotone_transport``: the ensemble transform particle filter's barycentric
projection, Reich 2013, exact and cheap in 1-D). Ranks are kept in every coordinate, so the
dependence between neighbours survives the update; no particle is resampled or duplicated.

It needs no network and no training, and its transport has no error beyond the weights'. What it
cannot do is what every particle filter cannot: where the local likelihood is sharp against the
spread of the ensemble, the weights collapse and so does the ensemble (Lorenz-96 at N = 100:
RMSE near climatology). Assimilate most of the likelihood with the LETKF first and the rest with
this (the hybrid of Chustagulprom, Reich & Reinhardt 2016; ``split_likelihood``): the LETKF moves
the ensemble under the likelihood and the transport adds the shape the Gaussian step cannot.

O(n N (K + log N)) work per update (K observations per coordinate), one ``vmap`` over the
coordinates or ``lax.map`` over batches of them (``batch_size``). Padding particles (``updates.base``)
take no part and come back unchanged; a missing component (NaN) is left out of every weight.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import inflate
from ot_filter.lib.monotone import monotone_transport
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_int, check_number
from ot_filter.lib.weights import active_mask, count_active, effective_sample_size
from ot_filter.localisation import Localisation, check_localisation, check_localised_analysis
from ot_filter.model import StateSpaceModel, observed_noise_factors, whiten
from ot_filter.updates.base import BayesUpdate, UniformWeightsState, uniform_weights_init
from ot_filter.updates.letkf import LETKFSettings

Array = jax.Array

__all__ = ["LocalETPFInfo", "LocalETPFSettings", "local_etpf", "local_etpf_apply"]


# The LETKF's numbers, inflation and localisation (traced: a vmap over them is one program).
LocalETPFSettings = LETKFSettings


class LocalETPFInfo(NamedTuple):
    min_effective_fraction: Array  # min over coordinates of the local effective sample size / k
    mean_effective_fraction: Array  # its mean over coordinates


def local_etpf(localisation: Localisation, inflation: float = 1.0, batch_size: int | None = None) -> BayesUpdate:
    """Builds the localised ensemble transform particle filter's Bayes update (needs a model with
    additive Gaussian noise, h and R).

    Args:
      localisation: ``ot_filter.localisation(model.geometry, radius)``: the taper of the local
        log-likelihoods; its radius may be traced.
      inflation: multiplicative inflation (>= 1) of the prior anomalies; may be traced. Leave it
        1 after an LETKF that inflates (``split_likelihood``).
      batch_size: transport this many coordinates at a time (``lax.map``); bounds the memory at
        O(batch_size N K). Static.
    """
    check_localisation(localisation)
    if batch_size is not None:
        batch_size = check_int("batch_size", batch_size, minimum=1)
    settings = LocalETPFSettings(check_number("inflation", inflation, minimum=1.0), localisation)
    return BayesUpdate(uniform_weights_init, bind(local_etpf_apply, settings, batch_size=batch_size))


def local_etpf_apply(settings: LocalETPFSettings, key: Array, state: UniformWeightsState, particles: Array,
                     observation: Array, model: StateSpaceModel, *, batch_size: int | None):
    """One LETPF analysis (``local_etpf``'s ``apply`` with its settings and structure given)."""
    del key  # deterministic
    n = particles.shape[1]
    m = observation.shape[0]
    localisation = settings.localisation
    check_localised_analysis("local_etpf", localisation, model, n, m)
    dtype = particles.dtype
    active = active_mask(state.log_weights)
    num_active = count_active(state.log_weights)
    particles = jnp.where(active[:, None], inflate(particles, active, settings.inflation), particles)
    observed = jnp.isfinite(observation)
    residual = jnp.where(observed, observation - jax.vmap(model.observation_function)(particles), 0.0)
    whitened = jnp.where(observed, whiten(observed_noise_factors(model, observed, dtype), residual), 0.0)
    log_likelihood = -0.5 * whitened**2  # [N, m], 0 for missing components
    taper = localisation.weights().astype(dtype) * observed[localisation.neighbours]  # [n, K]

    def analyse(inputs):
        neighbours, weight, column = inputs  # [K], [K], [N]
        log_weights = jnp.where(active, log_likelihood[:, neighbours] @ weight, -jnp.inf)
        effective = effective_sample_size(log_weights) / jnp.asarray(num_active, dtype)
        return monotone_transport(column, log_weights, active), effective

    inputs = (localisation.neighbours, taper, particles.T)
    if batch_size is None:
        moved, effective = jax.vmap(analyse)(inputs)
    else:
        moved, effective = jax.lax.map(analyse, inputs, batch_size=batch_size)
    info = LocalETPFInfo(jnp.min(effective), jnp.mean(effective))
    return moved.T, state, info
