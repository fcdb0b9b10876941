"""An amortised LOCAL map: the localised OT update's shared networks trained offline.

Online, ``local_ot`` trains its shared map at every step from N particles' n local pairs, for
a few dozen iterations (Lorenz-96: N = 100, 64 iterations from fresh networks); that much
learning does not improve on the deterministic layer (docs/amortised.md, Lorenz-96). A model whose local
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

The recorded form (what a runner stores and reloads): a ``LocalMapConfig`` names the model and
the update's sizes, ``train_local_amortised(key, model, config, forecasts, ...)`` trains its map
in chunks with a held-out validation loss and returns a ``LocalMap`` (parameters, config,
record), ``amortised_local_ot(local_map, model, num_iterations)`` builds the filter's update
from it, and ``storage.save_local_map`` / ``load_local_map`` keep it on disk.
"""

from __future__ import annotations

import time
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.amortised.training import TrainingHistory
from ot_filter.lib.validation import check_int, check_number
from ot_filter.lib.weights import uniform_log_weights
from ot_filter.localisation import local_windows
from ot_filter.model import StateSpaceModel
from ot_filter.progress import report
from ot_filter.transport.saddle import Batch, SaddleParams, TrainingTrace, evaluate_saddle, train_saddle
from ot_filter.updates.local_ot import LocalOTUpdate, local_ot, local_pairs, local_update_parts
from ot_filter.updates.ot import init_training, networks, optimizers

Array = jax.Array

__all__ = ["LocalBank", "LocalMap", "LocalMapConfig", "amortised_local_ot", "local_bank", "local_bank_batch",
           "train_local_amortised", "train_local_map"]


class LocalMapConfig(NamedTuple):
    """What a local map is for and how its update is built (JSON-ready; ``local_ot``'s options)."""

    model: str  # the model's name, checked when a stored map is loaded
    state_dim: int
    observation_dim: int
    radius: float  # ``local_windows(model.geometry, radius, state_radius)``
    state_radius: float = 0.0
    width: int = 64
    num_blocks: int = 1
    activation: str = "relu"
    enkf_layer: bool | str = False
    taper: str = "step"
    prior_context: int = 8
    location_context: bool = False
    batch_size: int = 512
    inner_steps: int = 10
    potential_learning_rate: float = 3e-4
    potential_weight_decay: float = 1.0
    transport_learning_rate: float = 1e-3
    inflation: float = 1.0


# What fixes the networks' shapes and inputs: a map is used with these as it was trained.
NETWORK_FIELDS = ("model", "state_dim", "observation_dim", "radius", "state_radius", "width", "num_blocks",
                  "activation", "enkf_layer", "taper", "prior_context", "location_context")


class LocalMap(NamedTuple):
    params: SaddleParams  # the shared networks (standardised window coordinates)
    config: LocalMapConfig
    info: dict  # how it was trained (bank, iterations, seconds, validation loss)


def amortised_local_ot(local_map: LocalMap | LocalMapConfig, model: StateSpaceModel,
                       num_iterations: int | tuple[int, int] = 0, *, warm_start: bool = False,
                       **online) -> LocalOTUpdate:
    """The localised OT update of a local map's config on ``model``'s geometry, starting from the
    map (``initial_map``): ``num_iterations=0`` uses it as is (one forward pass a step), k > 0
    trains k iterations a step from it (``warm_start=False``: every step from the map, with fresh
    optimiser states). ``online``: ``local_ot``'s other options (thresholds), and the online
    iterations' ``batch_size``, ``inner_steps`` and learning rates, which default to the offline
    training's; not the networks or windows (``NETWORK_FIELDS``). A bare config gives the
    untrained update (the offline trainer's template)."""
    config = local_map.config if isinstance(local_map, LocalMap) else local_map
    if not isinstance(config, LocalMapConfig):
        raise TypeError(f"local_map must be a LocalMap or LocalMapConfig, got {type(local_map).__name__}")
    if getattr(model, "geometry", None) is None:
        raise ValueError("amortised_local_ot needs a model with a geometry (its windows)")
    fixed = sorted(set(online) & set(NETWORK_FIELDS))
    if fixed:
        raise ValueError(f"{fixed} are the map's (its config), not options of the online update")
    windows = local_windows(model.geometry, config.radius, config.state_radius)
    options = {k: v for k, v in config._asdict().items()
               if k not in ("model", "state_dim", "observation_dim", "radius", "state_radius")}
    options.update(online)
    if isinstance(local_map, LocalMap):
        return local_ot(windows, num_iterations=num_iterations, warm_start=warm_start, initial_map=local_map.params,
                        **options)
    return local_ot(windows, num_iterations=1 if num_iterations == 0 else num_iterations, warm_start=warm_start,
                    **options)


class LocalBank(NamedTuple):
    """The local pairs of E forecast ensembles (standardised, each with its own scaling)."""

    x: Array  # [E, N, n, S] each particle's window
    y: Array  # [E, N, n, C] its simulated local observations, slot mask and prior context
    layer_x: Array  # [E, N, n, S] the layer's inputs of each copy (``local_ot._LocalData``)
    layer_y: Array  # [E, N, n, C]
    gain: Array  # [E, n, S, C] each window's layer gain


def _refuse_fresh_observations(structure) -> None:
    if structure.fresh_observations:
        raise ValueError("the bank stores each pair's simulated observations: build the update without "
                         "fresh_observations")


def local_bank(key: Array, update: LocalOTUpdate, model: StateSpaceModel, forecasts: Array) -> LocalBank:
    """The local pairs ``update`` would train on at each forecast ensemble ``forecasts[E, N, n]``
    (inflated, observations simulated with a key per ensemble). Ensembles are processed one at
    a time (``lax.map``): the bank, not the work, is what holds memory."""
    numbers, structure = local_update_parts(update)
    _refuse_fresh_observations(structure)
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
    _refuse_fresh_observations(structure)
    batch_size = structure.batch_size if batch_size is None else batch_size
    init_key, train_key = jax.random.split(key)
    state = _init_local_training(numbers, structure, init_key, bank)
    state, trace = _train_local_chunk(train_key, state, numbers, bank, structure, batch_size, num_iterations)
    return state.params, trace


def train_local_amortised(key: Array, model: StateSpaceModel, config: LocalMapConfig, forecasts: Array,
                          num_iterations: int, *, validation_fraction: float = 0.2, chunks: int = 20,
                          validation_batches: int = 8) -> tuple[LocalMap, TrainingHistory]:
    """The map of ``config`` trained offline on the local pairs of ``forecasts[E, N, n]`` (ordered
    by simulation: the last ``validation_fraction`` of the ensembles, whole trajectories where
    it is a multiple of one's share, are held out), ``num_iterations`` in ``chunks``. After each
    chunk: J of the map on ``validation_batches`` fixed mini-batches of the held-out pairs, and a
    progress report (``ot_filter.progress``). Returns the map, with its record in ``info``, and
    the curves (J of each chunk's last training batch, smoothed; the validation J)."""
    if not isinstance(config, LocalMapConfig):
        raise TypeError(f"config must be a LocalMapConfig, got {type(config).__name__}")
    if forecasts.ndim != 3 or forecasts.shape[2] != config.state_dim:
        raise ValueError(f"forecasts must have shape [E, N, {config.state_dim}] (config.state_dim), got "
                         f"{forecasts.shape}")
    chunks = check_int("chunks", chunks)
    per_chunk = check_int("num_iterations", num_iterations) // chunks
    if per_chunk < 1:
        raise ValueError(f"num_iterations ({num_iterations}) must be at least chunks ({chunks})")
    check_number("validation_fraction", validation_fraction, 0.0, 1.0, strict_minimum=True)
    count = forecasts.shape[0]
    held = max(1, int(round(validation_fraction * count)))
    if held >= count:
        raise ValueError(f"validation_fraction = {validation_fraction} leaves no training ensemble of {count}")
    update = amortised_local_ot(config, model)
    numbers, structure = local_update_parts(update)
    bank_key, validation_key, init_key, train_key, check_key = jax.random.split(key, 5)
    started = time.perf_counter()
    bank = local_bank(bank_key, update, model, forecasts[: count - held])
    validation = local_bank(validation_key, update, model, forecasts[count - held:])
    state = _init_local_training(numbers, structure, init_key, bank)
    iterations, training_loss, validation_loss = [], [], []
    for chunk in range(chunks):
        state, trace = _train_local_chunk(jax.random.fold_in(train_key, chunk), state, numbers, bank, structure,
                                          structure.batch_size, per_chunk)
        value = _validate_local(check_key, state.params, validation, structure, validation_batches)
        iterations.append((chunk + 1) * per_chunk)
        training_loss.append(float(jnp.where(trace.finite, trace.smoothed_loss, jnp.inf)))
        validation_loss.append(float(value))
        report(chunk + 1, chunks)
    seconds = time.perf_counter() - started
    history = TrainingHistory(np.array(iterations), np.array(training_loss), np.array(validation_loss), seconds)
    info = {"iterations": iterations[-1], "ensembles": count - held, "validation_ensembles": held,
            "particles": int(forecasts.shape[1]), "seconds": seconds, "final_validation_loss": validation_loss[-1],
            "finite": bool(np.isfinite(validation_loss[-1]))}
    return LocalMap(state.params, config, info), history


def _init_local_training(numbers, structure, key, bank: LocalBank):
    return init_training(numbers.ot, structure, key, bank.x.shape[-1], bank.y.shape[-1], bank.x.dtype)


@partial(jax.jit, static_argnames=("structure", "batch_size", "num_iterations"))
def _train_local_chunk(key, state, numbers, bank, structure, batch_size, num_iterations):
    """``num_iterations`` outer iterations from ``state`` on mini-batches of the bank."""
    potential_net, transport_net = networks(structure)
    potential_optimizer, transport_optimizer = optimizers(numbers.ot, structure)
    return train_saddle(
        key, state, lambda k: local_bank_batch(k, bank, batch_size, structure.enkf_layer), num_iterations,
        potential_net=potential_net, transport_net=transport_net,
        potential_optimizer=potential_optimizer, transport_optimizer=transport_optimizer,
        inner_steps=structure.inner_steps, enkf_layer=structure.enkf_layer, record_length=num_iterations,
        cost_from_layer=True,
    )


@partial(jax.jit, static_argnames=("structure", "num_batches"))
def _validate_local(key, params, bank, structure, num_batches):
    """Mean J of fixed parameters on ``num_batches`` mini-batches of ``bank`` (the same batches
    at every call: the key is fixed)."""
    potential_net, transport_net = networks(structure)

    def one(batch_key):
        return evaluate_saddle(batch_key, params,
                               lambda k: local_bank_batch(k, bank, structure.batch_size, structure.enkf_layer),
                               potential_net=potential_net, transport_net=transport_net,
                               enkf_layer=structure.enkf_layer, cost_from_layer=True)

    return jnp.mean(jax.vmap(one)(jax.random.split(key, num_batches)))
