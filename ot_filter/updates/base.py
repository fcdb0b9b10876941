"""The interface every Bayes update implements (optax-style: a NamedTuple of pure functions).

    update = ot_filter.sir(...)                        # static configuration at build time
    state = update.init(key, particles, model)         # particles[N, n]
    particles, state, info = update.apply(key, state, particles, observation, model)

``apply`` maps prior particles (after propagation) and an observation ``y[m]`` to posterior
particles. Every state is a NamedTuple with a ``log_weights[N]`` field, normalised
(logsumexp = 0): the posterior is the weighted empirical measure
``sum_i exp(log_weights_i) delta_{X^i}`` (uniform except for SIR between resampling steps).
``info`` holds per-step diagnostics; ``run_filter`` stacks them. ``init`` is given the model
because some states depend on it (the OT update's networks need the observation dimension); SIR
and EnKF ignore it. An update may offer more than ``init``/``apply`` (``ot()`` returns an
``OTUpdate`` that also exposes its trained map); ``run_filter`` accepts any NamedTuple with these
two.

Padded particle axis (active-particle mask). A sweep over particle counts can run as ONE compiled
program: arrays are padded to ``N_max`` particles and only ``num_active`` of them (a traced int,
so it can be vmapped over) are real. The mask travels in the state's log-weights:

- A particle whose ``state.log_weights`` entry is -inf is padding; every other particle is
  active, and ``num_active = sum(log_weights > -inf)``. An active particle never has log-weight
  -inf (SIR gives a particle of zero likelihood the most negative finite log-weight instead).
- ``run_filter(..., num_active=k)`` sets, after ``update.init``, ``log_weights`` to ``-log k`` on
  the first k entries and -inf on the other ``N_max - k`` (``uniform_log_weights(particles, k)``),
  through ``state._replace(log_weights=...)``.
- ``apply`` must ignore padding in every statistic (means, covariances, gains, resampling,
  effective sample size, kernel bandwidths: with k, not N_max, wherever the particle count
  appears), return padding at log-weight -inf and keep the active log-weights normalised
  (logsumexp over the active ones = 0). Padding values may be anything finite (copies of other
  particles, stale values): they must not change the result for the active particles. An update
  may move the padding (SIR's resampling writes its k draws into the first k slots), provided
  the particles and log-weights it returns agree; it should leave padding finite and bounded
  (SIR: copies of the draws; EnKF: the posterior mean), since ``run_filter`` keeps propagating it.
- k is traced: shapes stay N_max, statistics use ``where(active, ., 0)`` sums divided by k
  (``where``, not a product with 0, which inf or NaN padding would poison) and random numbers
  are drawn for all N_max particles, the first k used: ``jax.random`` streams are
  prefix-consistent, so a padded run then reproduces the unpadded k-particle run with the same
  key (up to rounding; SIR's resampling can flip an index at a rounding boundary).
- ``active_mask`` and ``count_active`` read the mask; ``uniform_log_weights(particles, k)``
  builds it. With no padding the results are those of the unpadded code (see
  ``count_dependent`` for the last bits).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

Array = jax.Array


class BayesUpdate(NamedTuple):
    """A Bayes update: ``init(key, particles, model=None) -> state`` and
    ``apply(key, state, particles, observation, model) -> (particles, state, info)``."""

    init: Callable[..., Any]  # (key, particles, model=None) -> state
    apply: Callable[..., tuple[Array, Any, Any]]


class UniformWeightsState(NamedTuple):
    """State of updates whose active particles are equally weighted (EnKF)."""

    log_weights: Array  # [N]: -log(num_active) on the active particles, -inf on padding


def active_mask(log_weights: Array) -> Array:
    """``[N]`` bool, False for padding (log-weight -inf)."""
    return log_weights > -jnp.inf


def count_active(log_weights: Array) -> Array:
    """The number of active particles, an int32 scalar (traced inside jit)."""
    return jnp.sum(active_mask(log_weights), dtype=jnp.int32)


def count_dependent(formula: Callable[[Any], Any], num_active: Array, num_particles: int):
    """``formula(num_active)``, but ``formula(num_particles)`` on the Python int when nothing is
    padded (``num_active == num_particles``).

    Inside jit XLA folds an expression of a static count into constants and rewrites a division
    by one into a multiplication by its reciprocal, which can differ by an ulp from the same
    formula of a traced count (e.g. -log 7, x / 7). Taking the static branch when nothing is
    padded keeps unpadded results what they were before padding existed: bit for bit for SIR;
    for the EnKF the masking ``where``s change how XLA fuses (and contracts into FMAs) the
    surrounding arithmetic, so jitted unpadded EnKF runs may differ in the last bits. Both
    branches are computed: keep ``formula`` cheap (divisions, not the matrix products feeding
    them).
    """
    return jnp.where(num_active == num_particles, formula(num_particles), formula(num_active))


def uniform_log_weights(particles: Array, num_active: Array | int | None = None) -> Array:
    """``[N]`` equal log-weights ``-log N``; with ``num_active = k``, ``-log k`` on the first k
    entries and -inf (padding) on the rest."""
    num_particles = particles.shape[0]
    if num_active is None:
        return jnp.full((num_particles,), -jnp.log(num_particles), dtype=particles.dtype)
    value = count_dependent(lambda count: -jnp.log(count), num_active, num_particles)
    return jnp.where(jnp.arange(num_particles) < num_active, value, -jnp.inf).astype(particles.dtype)
