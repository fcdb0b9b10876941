"""Importance sampling with resampling (SIR): the chapter's Bayes update by reweighting.

Step 1 (importance weights, chapter Sec. "Bayes update using importance sampling"):

    log w^i <- log w^i + log l(y | X^i),   normalised by logsumexp (never exponentiated raw).

The log of the normaliser, ``log sum_i w^i_prev l(y | X^i)``, is the estimate of the incremental
marginal likelihood ``log p(y_t | y_{1:t-1})`` (summed over t: the marginal log-likelihood).

Step 2 (resampling) when the effective sample size ESS = 1 / sum_i (w^i)^2 falls below
``ess_threshold * N`` (threshold 1.0: every step); otherwise the weights are carried.

Regularisation (DAPPER's ``PartFilt(reg=...)``): after resampling, add Gaussian jitter with
covariance ``(jitter * N^(-1/(n+4)))^2 * C`` where C is the (unbiased) weighted covariance of the
ensemble before resampling (the equally weighted one if a single particle holds all the mass)
and ``N^(-1/(n+4))`` is Scott's kernel-bandwidth rule. It keeps resampled duplicates apart when
the dynamics are deterministic. Unlike DAPPER's default (``nuj=True``), every particle is
jittered, not only the duplicated ones.

Degenerate weights (all log-likelihoods -inf or NaN, or +inf) cannot be normalised: the update
is then skipped (the prior weights are kept), ``info.degenerate`` is set and nothing becomes NaN.

Padded particle axis (``updates.base``): particles of prior log-weight -inf are padding and
N above becomes the number k of active particles everywhere. Padding keeps weight -inf whatever
its likelihood; the ESS threshold is ``ess_threshold * k``; resampling makes k draws among the
active particles into the first k slots (the comb has k teeth; the padding slots get copies of
the draws, at log-weight -inf); the jitter bandwidth is ``k^(-1/(n+4))`` and C is the weighted
covariance of the active particles. Since -inf marks padding, an active particle of zero
likelihood gets the most negative finite log-weight instead (its weight is still exactly 0).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import weighted_covariance
from ot_filter.lib.linalg import psd_sqrt
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_number, is_traced
from ot_filter.lib.weights import (
    active_mask,
    count_active,
    count_dependent,
    effective_sample_size,
    normalise_log_weights,
    uniform_log_weights,
)
from ot_filter.model import StateSpaceModel
from ot_filter.sharding import replicated
from ot_filter.updates.base import BayesUpdate
from ot_filter.updates.resampling import RESAMPLING_SCHEMES

Array = jax.Array

__all__ = ["SIRInfo", "SIRSettings", "SIRState", "sir", "sir_apply", "sir_init"]


class SIRState(NamedTuple):
    log_weights: Array  # [N], normalised over the active particles, -inf on padding


class SIRInfo(NamedTuple):
    log_likelihood_increment: Array  # scalar: log p(y_t | y_{1:t-1}) estimate (-inf if degenerate)
    ess: Array  # scalar: effective sample size after reweighting, before resampling
    resampled: Array  # bool scalar
    degenerate: Array  # bool scalar: weights could not be normalised, update skipped


class SIRSettings(NamedTuple):
    """SIR's numbers (traced: ``vmap`` over them runs in one program)."""

    ess_threshold: Array  # resample when ESS < ess_threshold * N
    jitter: Array  # regularisation scale (DAPPER's ``reg``)


def sir(
    resampling: str = "systematic",
    ess_threshold: float = 1.0,
    jitter: float = 0.0,
) -> BayesUpdate:
    """Builds the SIR (bootstrap particle filter) Bayes update.

    Args:
      resampling: 'systematic' (default), 'multinomial', 'stratified' or 'residual'. Static.
      ess_threshold: resample when ESS < ess_threshold * N; 1.0 resamples every step, 0.0 never.
        May be traced; a concrete 1.0 compiles the resampling without its ``cond``.
      jitter: regularisation scale (DAPPER's ``reg``); 0 disables it. May be traced; a
        concrete 0 compiles no regularisation at all.
    """
    if resampling not in RESAMPLING_SCHEMES:
        raise ValueError(f"resampling must be one of {sorted(RESAMPLING_SCHEMES)}, got {resampling!r}")
    ess_threshold = check_number("ess_threshold", ess_threshold, minimum=0.0, maximum=1.0)
    jitter = check_number("jitter", jitter, minimum=0.0)
    # Concrete values that switch a part off keep it out of the program (as before numbers were
    # traced); a traced value compiles the general form, which gives the same numbers.
    always_resample = not is_traced(ess_threshold) and float(ess_threshold) >= 1.0
    regularised = is_traced(jitter) or float(jitter) > 0.0
    apply = bind(
        sir_apply, SIRSettings(ess_threshold, jitter), resampling=resampling,
        always_resample=always_resample, regularised=regularised,
    )
    return BayesUpdate(bind(sir_init), apply)


def sir_init(key: Array, particles: Array, model: StateSpaceModel | None = None) -> SIRState:
    del key, model
    return SIRState(uniform_log_weights(particles))


def sir_apply(settings: SIRSettings, key: Array, state: SIRState, particles: Array,
              observation: Array, model: StateSpaceModel, *, resampling: str,
              always_resample: bool, regularised: bool):
    """One SIR analysis (``sir``'s ``apply`` with its settings and structure given)."""
    if model.log_likelihood is None:
        raise ValueError(
            "sir needs model.log_likelihood (the analytical setting); this model only has a "
            "simulator: use enkf or ot instead"
        )
    resample_scheme = RESAMPLING_SCHEMES[resampling]
    num_particles = particles.shape[0]
    active = active_mask(state.log_weights)
    num_active = count_active(state.log_weights)
    log_likelihoods = jax.vmap(model.log_likelihood, (None, 0))(observation, particles)
    log_likelihoods = jnp.where(jnp.isnan(log_likelihoods), -jnp.inf, log_likelihoods)
    # `where`, not -inf + log l: a padding likelihood of +inf must not give NaN.
    unnormalised = jnp.where(active, state.log_weights + log_likelihoods, -jnp.inf)
    # Sharded particles: the N weights on every device, so that their normalisation, the ESS
    # and the resampling round as on one device (a no-op without a mesh; sharding.py).
    unnormalised = replicated(unnormalised)
    normalised, increment = normalise_log_weights(unnormalised)  # prior weights are normalised
    degenerate = ~jnp.isfinite(increment)
    log_weights = jnp.where(degenerate, state.log_weights, normalised)
    smallest = jnp.finfo(log_weights.dtype).min  # exp(smallest) = 0, but it is not padding
    log_weights = jnp.where(active, jnp.maximum(log_weights, smallest), -jnp.inf)
    ess = effective_sample_size(log_weights)

    def resample(key, particles, log_weights):
        resample_key, jitter_key = jax.random.split(key)
        resampled = particles[resample_scheme(resample_key, log_weights, num_active)]
        if regularised:
            resampled = resampled + _regularisation_noise(
                jitter_key, particles, log_weights, settings.jitter, num_active
            )
        return resampled, uniform_log_weights(particles, num_active)

    if always_resample:
        do_resample = jnp.asarray(True)
        particles, log_weights = resample(key, particles, log_weights)
    else:
        threshold = count_dependent(
            lambda count: settings.ess_threshold * count, num_active, num_particles
        )
        do_resample = (ess < threshold) | (settings.ess_threshold >= 1.0)
        particles, log_weights = jax.lax.cond(
            do_resample, resample, lambda _, x, lw: (x, lw), key, particles, log_weights
        )
    info = SIRInfo(increment, ess, do_resample, degenerate)
    return particles, SIRState(log_weights), info


def _regularisation_noise(key, particles, log_weights, jitter, num_active=None):
    """Gaussian noise ~ N(0, (jitter * k^(-1/(n+4)))^2 C_w), C_w the weighted covariance and k
    the number of active particles (``num_active``; None: all N)."""
    num_particles, dim = particles.shape
    covariance = weighted_covariance(particles, log_weights)
    exponent = -1.0 / (dim + 4)
    scale = jitter * num_particles**exponent
    if num_active is not None:
        scale = count_dependent(lambda count: jitter * count**exponent, num_active, num_particles)
    standard = jax.random.normal(key, particles.shape, particles.dtype)
    return scale * standard @ psd_sqrt(covariance).T
