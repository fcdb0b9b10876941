"""The offline training data of an amortised OT map: a bank of forecast ensembles.

A filter's OT update sees, at every step, a forecast ensemble X^1..X^N; it standardises it (per
coordinate, ``transport/standardisation.py``) and transports it with a map T(x, y) trained on
pairs (X^i, Y^i), Y^i ~ h(. | X^i). An amortised map is trained once on the forecast ensembles a
filter meets along long trajectories of the model: each ensemble is stored with its own
standardisation (and EnKF-layer gain, and context), and every mini-batch draws its joint pairs and its
independent copies Xbar from the SAME ensemble, so that the map learns to condition the prior
it is applied to, in that prior's standardised coordinates, for the ensembles the filter meets.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import inflate
from ot_filter.model import StateSpaceModel, simulate_observations
from ot_filter.transport.batches import simulate_standardised
from ot_filter.transport.context import ContextScaling, context_features
from ot_filter.transport.saddle import Batch, enkf_gain
from ot_filter.transport.standardisation import Standardisation, standardisation

Array = jax.Array

__all__ = ["ForecastBank", "bank_batch", "forecast_bank", "split_bank"]


class ForecastBank(NamedTuple):
    """E forecast ensembles of N particles, each with what the online update computes from it."""

    particles: Array  # [E, N, n] forecast ensembles (inflated as the update inflates them)
    scaling: Standardisation  # leaves [E, ...]: each ensemble's standardisation
    gain: Array  # [E, n, m] each ensemble's EnKF-layer gain (standardised coordinates)
    context: Array  # [E, c] each ensemble's context features (``transport/context.py``), raw

    @property
    def num_ensembles(self) -> int:
        return self.particles.shape[0]


@jax.jit
def forecast_bank(key: Array, model: StateSpaceModel, analyses: Array, inflation=1.0) -> ForecastBank:
    """The forecasts of analysis ensembles ``[..., N, n]`` (any leading axes, e.g. simulations
    and steps of ``run_filter``'s saved particles): each propagated one step by the model,
    inflated, standardised with observations simulated at it, and its EnKF-layer gain."""
    num, n = analyses.shape[-2:]
    analyses = analyses.reshape(-1, num, n)
    keys = jax.random.split(key, analyses.shape[0])

    def one(key, ensemble):
        propagate_key, observe_key = jax.random.split(key)
        forecast = jax.vmap(model.sample_transition)(jax.random.split(propagate_key, num), ensemble)
        active = jnp.ones(num, bool)
        forecast = inflate(forecast, active, inflation)
        simulated = simulate_observations(observe_key, model, forecast)
        scaling = standardisation(forecast, simulated, active)
        xs = scaling.standardise_x(forecast)
        gain = enkf_gain(xs, scaling.standardise_y(simulated))
        return ForecastBank(forecast, scaling, gain, context_features(scaling, xs))

    return jax.vmap(one)(keys, analyses)


def split_bank(bank: ForecastBank, validation_fraction: float) -> tuple[ForecastBank, ForecastBank]:
    """``(training, validation)``: the last ``validation_fraction`` of the ensembles held out
    (the bank is ordered by simulation, so these are whole held-out trajectories when the
    fraction is a multiple of one simulation's share)."""
    count = bank.num_ensembles
    held = max(1, int(round(validation_fraction * count)))
    if held >= count:
        raise ValueError(f"validation_fraction = {validation_fraction} leaves no training ensemble of {count}")
    return (jax.tree.map(lambda leaf: leaf[: count - held], bank),
            jax.tree.map(lambda leaf: leaf[count - held:], bank))


def bank_batch(key: Array, bank: ForecastBank, sample_observation: Callable, *, batch_size: int,
               ensembles_per_batch: int, enkf_layer: bool, context_scaling: ContextScaling | None = None) -> Batch:
    """One mini-batch: ``ensembles_per_batch`` ensembles drawn at random, from each
    ``batch_size // ensembles_per_batch`` joint pairs and as many independent copies of the same
    ensemble, observations simulated afresh (standardised with that ensemble's scaling); with the
    EnKF layer, each pair carries its ensemble's gain; with ``context_scaling``, its ensemble's
    normalised context."""
    per_ensemble = batch_size // ensembles_per_batch
    ensemble_key, pair_key, copy_key, y_key, ybar_key = jax.random.split(key, 5)
    chosen = jax.random.randint(ensemble_key, (ensembles_per_batch,), 0, bank.num_ensembles)
    num = bank.particles.shape[1]

    def from_ensemble(index, pair_key, copy_key, y_key, ybar_key):
        particles = bank.particles[index]
        scaling = jax.tree.map(lambda leaf: leaf[index], bank.scaling)
        x = scaling.standardise_x(particles[jax.random.randint(pair_key, (per_ensemble,), 0, num)])
        xbar = scaling.standardise_x(particles[jax.random.randint(copy_key, (per_ensemble,), 0, num)])
        y = simulate_standardised(y_key, sample_observation, scaling, x)
        ybar = simulate_standardised(ybar_key, sample_observation, scaling, xbar)
        gain = jnp.broadcast_to(bank.gain[index], (per_ensemble,) + bank.gain.shape[1:])
        context = jnp.broadcast_to(bank.context[index], (per_ensemble,) + bank.context.shape[1:])
        return x, y, xbar, ybar, gain, context

    keys = [jax.random.split(k, ensembles_per_batch) for k in (pair_key, copy_key, y_key, ybar_key)]
    x, y, xbar, ybar, gain, context = jax.vmap(from_ensemble)(chosen, *keys)
    flat = lambda a: a.reshape((-1,) + a.shape[2:])  # noqa: E731
    return Batch(flat(x), flat(y), flat(xbar), flat(ybar), flat(gain) if enkf_layer else None,
                 None if context_scaling is None else context_scaling.normalise(flat(context)))
