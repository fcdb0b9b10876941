"""Bayes' formula in several steps: the likelihood split into powers, each assimilated by its own
update on the output of the one before.

    p(x | y)  ∝  p(x) l(y | x)^a_1 ... l(y | x)^a_J,    a_1 + ... + a_J = 1.

With additive Gaussian noise, l(y | x)^a is (up to a constant) the likelihood of the same model
with noise covariance R / a (``tempered_model``), so each step is an ordinary update of an
ordinary model and the split is exact whenever the steps are. Why split: the updates fail in
different ways. The LETKF is exact only for Gaussians; a particle filter is exact for any shape
but collapses when the likelihood is sharp against the ensemble. The LETKF on most of the
likelihood and a particle filter (``local_etpf``) on the rest is the hybrid of Chustagulprom,
Reich & Reinhardt (2016): on Lorenz-96 with y = |x| its RMSE is 0.69 of the LETKF's
(``docs/ot_at_scale.md``).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp

from ot_filter.lib.static import bind, functions_as_pytrees
from ot_filter.lib.validation import check_number, is_traced
from ot_filter.model import StateSpaceModel, colour_noise, observation_noise_factors
from ot_filter.updates.base import BayesUpdate

Array = jax.Array

__all__ = ["SplitLikelihoodInfo", "SplitLikelihoodState", "split_likelihood", "tempered_model"]


class SplitLikelihoodState(NamedTuple):
    log_weights: Array  # [N]: the last step's
    states: tuple  # each step's state


class SplitLikelihoodInfo(NamedTuple):
    steps: tuple  # each step's info


def tempered_model(model: StateSpaceModel, power) -> StateSpaceModel:
    """``model`` with its likelihood raised to ``power`` (> 0; may be traced): additive Gaussian
    noise with covariance R / power, in every field an update reads (R and its factors,
    ``sample_observation``, ``log_likelihood``, which drops its normalising constant's change).
    ``parameters`` stay as they are (a linear-Gaussian model's matrices for ``kalman_filter``)."""
    if not model.has_gaussian_observation_noise:
        raise ValueError("a tempered likelihood needs additive Gaussian observation noise: give "
                         "model.observation_function and model.observation_noise_cov")
    power = check_number("power", power, minimum=0.0, strict_minimum=True)
    factors = model.observation_noise_factors
    if factors is not None:
        factors = (factors[0] / jnp.sqrt(power), factors[1] * jnp.sqrt(power))
    tempered = model._replace(observation_noise_cov=jnp.asarray(model.observation_noise_cov) / power,
                              observation_noise_factors=factors)
    observe = model.observation_function

    def sample_observation(key, x):
        predicted = observe(x)
        standard = jax.random.normal(key, predicted.shape, predicted.dtype)
        return predicted + colour_noise(observation_noise_factors(tempered, predicted.dtype), standard)

    def log_likelihood(y, x):
        return power * model.log_likelihood(y, x)

    return tempered._replace(sample_observation=sample_observation,
                             log_likelihood=None if model.log_likelihood is None else log_likelihood)


def split_likelihood(updates: Sequence[Any], powers: Sequence[float]) -> BayesUpdate:
    """Builds the update that assimilates ``l(y | x)^powers[j]`` with ``updates[j]``, in order
    (needs a model with additive Gaussian noise).

    Args:
      updates: Bayes updates (``BayesUpdate``-like NamedTuples of ``init`` and ``apply``); each
        step's output particles and log-weights are the next one's state. Only an update that
        weighs (``sir``) reads the weights; ``enkf``, ``letkf`` and ``local_etpf`` read them
        as the active-particle mask only and treat the particles as equally weighted, so an
        update that may leave unequal weights must come last (and, in a filter, a step that
        does not read them must not follow it at the next time either: use ``sir`` with
        resampling there).
      powers: one positive number per update, summing to 1; may be traced (a vmap over the split
        is one program).

    Info: ``SplitLikelihoodInfo(steps)``, each step's info.
    """
    updates = tuple(updates)
    powers = tuple(powers)
    if not updates:
        raise ValueError("updates must hold at least one update")
    if len(powers) != len(updates):
        raise ValueError(f"powers must have one entry per update ({len(updates)}), got {len(powers)}")
    for index, update in enumerate(updates):
        if not (hasattr(update, "init") and hasattr(update, "apply") and hasattr(update, "_fields")):
            raise TypeError(f"updates[{index}] must be a Bayes update (a NamedTuple with init and apply), "
                            f"got {type(update).__name__}")
    powers = tuple(check_number(f"powers[{index}]", power, minimum=0.0, strict_minimum=True)
                   for index, power in enumerate(powers))
    if not any(is_traced(power) for power in powers) and abs(sum(powers) - 1.0) > 1e-6:
        raise ValueError(f"powers must sum to 1, got {powers} (sum {sum(powers)})")
    settings = (powers, tuple(functions_as_pytrees(update) for update in updates))
    return BayesUpdate(bind(_init, settings), bind(_apply, settings))


def _init(settings, key, particles, model):
    powers, updates = settings
    keys = jax.random.split(key, len(updates))
    states = tuple(update.init(one, particles, tempered_model(model, power))
                   for update, power, one in zip(updates, powers, keys))
    return SplitLikelihoodState(states[-1].log_weights, states)


def _apply(settings, key, state, particles, observation, model):
    powers, updates = settings
    keys = jax.random.split(key, len(updates))
    log_weights = state.log_weights
    states, infos = [], []
    for update, power, step_state, one in zip(updates, powers, state.states, keys):
        step_state = step_state._replace(log_weights=log_weights)
        particles, step_state, info = update.apply(one, step_state, particles, observation,
                                                   tempered_model(model, power))
        log_weights = step_state.log_weights
        states.append(step_state)
        infos.append(info)
    return particles, SplitLikelihoodState(log_weights, tuple(states)), SplitLikelihoodInfo(tuple(infos))
