"""The interface every Bayes update implements (optax-style: a NamedTuple of pure functions).

    update = ot_filter.sir(...)                        # static configuration at build time
    state = update.init(key, particles, model)         # particles[N, n]
    particles, state, info = update.apply(key, state, particles, observation, model)

``apply`` maps prior particles (after propagation) and an observation ``y[m]`` to posterior
particles. Components of y that are NaN are missing: ``apply`` must assimilate the others, with
the result of the model whose observation has those components deleted (the Kalman filter, the
EnKFs, the LETKF and SIR do, with masks: a changing set of observed components does not
recompile; the OT update learns the map conditioned on the observed components, so it gives that
result up to its training error). ``run_filter``
never calls ``apply`` with every component missing. Every state is a NamedTuple with a ``log_weights[N]`` field, normalised
(logsumexp = 0): the posterior is the weighted empirical measure
``sum_i exp(log_weights_i) delta_{X^i}`` (uniform except for SIR between resampling steps).
``run_filter`` checks that contract when it traces ``init`` (a TypeError names it otherwise) and
carries the particles with those log-weights as one ``particles.ParticleState``. ``info`` holds
per-step diagnostics; ``run_filter`` stacks them. ``init`` is given the model
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

from ot_filter.lib.static import bind
from ot_filter.lib.weights import (
    active_mask,
    count_active,
    count_dependent,
    uniform_log_weights,
)

__all__ = [  # the contract's helpers are re-exported from lib.weights
    "BayesUpdate",
    "UniformWeightsState",
    "active_mask",
    "count_active",
    "count_dependent",
    "init_uniform_weights",
    "uniform_log_weights",
    "uniform_weights_init",
]

Array = jax.Array


class BayesUpdate(NamedTuple):
    """A Bayes update: ``init(key, particles, model=None) -> state`` and
    ``apply(key, state, particles, observation, model) -> (particles, state, info)``.

    The built-in builders bind module-level functions with ``lib.static.bind``: an update is then
    a pytree whose leaves are its numeric settings (traced inside jit, so ``vmap`` over them
    works and a new value does not recompile) and whose static part is its structure."""

    init: Callable[..., Any]  # (key, particles, model=None) -> state
    apply: Callable[..., tuple[Array, Any, Any]]


class UniformWeightsState(NamedTuple):
    """State of updates whose active particles are equally weighted (EnKF)."""

    log_weights: Array  # [N]: -log(num_active) on the active particles, -inf on padding


def init_uniform_weights(key: Array, particles: Array, model=None) -> UniformWeightsState:
    """``init`` of the updates whose state is equal log-weights only (EnKF)."""
    del key, model
    return UniformWeightsState(uniform_log_weights(particles))


uniform_weights_init = bind(init_uniform_weights)
