"""An amortised LOCAL map: the localised OT update's shared networks trained offline.

Online, ``local_ot`` trains its shared map at every step from N particles' n local pairs, for
a few dozen iterations (Lorenz-96: N = 100, 64 iterations from fresh networks); that much
learning does not improve on the deterministic layer (README, Lorenz-96). A model whose local
problems are alike along a trajectory (a homogeneous ring after a burn-in) lets the map learn
them once, offline, from the local pairs of many forecast ensembles:

    bank = local_bank(key, update, model, forecasts)        # forecasts [E, N, n]
    params, trace = train_local_map(key, update, bank, num_iterations=20_000)
    amortised = local_ot(windows, ..., initial_map=params)  # the same options as ``update``

Each mini-batch row is one (ensemble, particle, coordinate) with its independent copy Xbar drawn
from the same ensemble at the same coordinate (that local problem's independent coupling), the
ensemble's own standardisation, layer and prior context: what one step of ``local_ot`` trains on,
pooled over the bank. ``local_ot(..., initial_map=params, num_iterations=0)`` then filters with
one forward pass a step; ``num_iterations=k`` fine-tunes from the map at every step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.weights import uniform_log_weights
from ot_filter.model import StateSpaceModel
from ot_filter.transport.saddle import Batch, SaddleParams, TrainingTrace, train_saddle
from ot_filter.updates.local_ot import LocalOTUpdate, local_pairs, local_update_parts
from ot_filter.updates.ot import init_training, networks, optimizers

Array = jax.Array

__all__ = ["LocalBank", "local_bank", "local_bank_batch", "train_local_map"]


class LocalBank(NamedTuple):
    """The local pairs of E forecast ensembles (standardised, each with its own scaling)."""

    x: Array  # [E, N, n, S] each particle's window
    y: Array  # [E, N, n, C] its simulated local observations, slot mask and prior context
    layer_x: Array  # [E, N, n, S] the layer's inputs of each copy (``local_ot._LocalData``)
    layer_y: Array  # [E, N, n, C]
    gain: Array  # [E, n, S, C] each window's layer gain


def local_bank(key: Array, update: LocalOTUpdate, model: StateSpaceModel, forecasts: Array) -> LocalBank:
    """The local pairs ``update`` would train on at each forecast ensemble ``forecasts[E, N, n]``
    (inflated, observations simulated with a key per ensemble). Ensembles are processed one at
    a time (``lax.map``): the bank, not the work, is what holds memory."""
    numbers, structure = local_update_parts(update)
    if forecasts.ndim != 3:
        raise ValueError(f"forecasts must have shape [E, N, n], got {forecasts.shape}")
    m = jax.eval_shape(model.sample_observation, key, forecasts[0, 0]).shape[0]

    @jax.jit
    def pairs(keys, forecasts):
        def one(args):
            key, ensemble = args
            _, data = local_pairs(numbers, structure, key, uniform_log_weights(ensemble), ensemble,
                                  jnp.zeros((m,), ensemble.dtype), model)
            return LocalBank(data.x, data.y, data.layer_x, data.layer_y, data.gain)

        return jax.lax.map(one, (keys, forecasts))

    return pairs(jax.random.split(key, forecasts.shape[0]), forecasts)


def local_bank_batch(key: Array, bank: LocalBank, batch_size: int, use_gain: bool) -> Batch:
    """One mini-batch of ``batch_size`` local pairs drawn across the bank (module docstring)."""
    ensemble_key, pair_key, copy_key, coordinate_key = jax.random.split(key, 4)
    num_ensembles, num, n = bank.x.shape[:3]
    shape = (batch_size,)
    ensemble = jax.random.randint(ensemble_key, shape, 0, num_ensembles)
    coordinate = jax.random.randint(coordinate_key, shape, 0, n)
    pair = jax.random.randint(pair_key, shape, 0, num)
    copy = jax.random.randint(copy_key, shape, 0, num)
    return Batch(bank.x[ensemble, pair, coordinate], bank.y[ensemble, pair, coordinate],
                 bank.layer_x[ensemble, copy, coordinate], bank.layer_y[ensemble, copy, coordinate],
                 bank.gain[ensemble, coordinate] if use_gain else None)


def train_local_map(key: Array, update: LocalOTUpdate, bank: LocalBank, num_iterations: int, *,
                    batch_size: int | None = None) -> tuple[SaddleParams, TrainingTrace]:
    """The shared networks of ``update`` (its widths, optimisers, inner steps and layer) trained
    for ``num_iterations`` outer iterations on mini-batches of the bank (``batch_size``: the
    update's unless given). Returns the parameters and the trace (J of every iteration)."""
    numbers, structure = local_update_parts(update)
    batch_size = structure.batch_size if batch_size is None else batch_size
    window, conditioning = bank.x.shape[-1], bank.y.shape[-1]
    potential_net, transport_net = networks(structure)
    potential_optimizer, transport_optimizer = optimizers(numbers.ot, structure)
    init_key, train_key = jax.random.split(key)

    @jax.jit
    def run(init_key, train_key, bank):
        state = init_training(numbers.ot, structure, init_key, window, conditioning, bank.x.dtype)
        state, trace = train_saddle(
            train_key, state, lambda k: local_bank_batch(k, bank, batch_size, structure.enkf_layer), num_iterations,
            potential_net=potential_net, transport_net=transport_net,
            potential_optimizer=potential_optimizer, transport_optimizer=transport_optimizer,
            inner_steps=structure.inner_steps, enkf_layer=structure.enkf_layer, record_length=num_iterations,
            cost_from_layer=True,
        )
        return state.params, trace

    return run(init_key, train_key, bank)
