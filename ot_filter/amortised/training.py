"""Offline training of an amortised OT map, and the map it produces.

``collect_forecasts`` runs a filter over simulated trajectories of the model and keeps the
forecast ensembles it meets (``bank.py``); ``train_map`` trains the conditional map on them with
the online update's saddle-point machinery (``transport/saddle.py``), in compiled chunks of
iterations with a held-out validation loss (J on fixed mini-batches of held-out trajectories)
after each. ``train_amortised`` does both in rounds: the first bank comes from a cheap filter
(the EnKF), each later one from the amortised filter itself with the map of the round before
(so that the map is trained on the ensembles it will meet: a map trained only on EnKF forecasts
sees ensembles online that it never saw). The result, ``AmortisedMap``, is what
``ot_filter.amortised_ot`` filters with and what ``storage.save_map`` writes.
"""

from __future__ import annotations

import time
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.amortised.bank import ForecastBank, bank_batch, forecast_bank, split_bank
from ot_filter.filtering import run_filter
from ot_filter.lib.validation import check_int, check_number
from ot_filter.model import StateSpaceModel, simulate
from ot_filter.progress import report
from ot_filter.transport.context import ContextScaling, context_size, fit_context_scaling
from ot_filter.transport.networks import ACTIVATIONS
from ot_filter.transport.saddle import SaddleParams, TrainingState, evaluate_saddle, train_saddle
from ot_filter.updates.ot import OTSettings, OTStructure, init_training, networks, optimizers, recipe

Array = jax.Array

__all__ = ["AmortisedMap", "MapConfig", "TrainingHistory", "collect_forecasts", "map_recipe",
           "train_amortised", "train_map"]


class MapConfig(NamedTuple):
    """What an amortised map is (JSON-ready: saved beside the parameters and checked at load)."""

    model: str  # the model's name as the caller gives it (e.g. "dynamic-n10", "lorenz63-x1")
    state_dim: int
    observation_dim: int
    width: int
    num_blocks: int
    activation: str
    enkf_layer: bool
    inner_steps: int
    batch_size: int
    potential_learning_rate: float
    potential_weight_decay: float
    transport_learning_rate: float
    inflation: float
    context: bool  # the networks also read each prior's context (``transport/context.py``)


class AmortisedMap(NamedTuple):
    params: SaddleParams  # f's and T's flax parameters (standardised coordinates)
    context_scaling: ContextScaling | None  # normalises the context features (None: no context)
    config: MapConfig
    info: dict  # how it was trained (iterations, rounds, seconds, validation loss, versions)


class TrainingHistory(NamedTuple):
    iterations: np.ndarray  # [C] iterations done at the end of each chunk
    training_loss: np.ndarray  # [C] smoothed J of the training mini-batches
    validation_loss: np.ndarray  # [C] mean J on the held-out mini-batches
    seconds: float


def map_recipe(config: MapConfig, num_iterations: int = 1,
               context_scaling: ContextScaling | None = None) -> tuple[OTSettings, OTStructure]:
    """The OT update's (settings, structure) of a map: its networks and optimisers (the context
    scaling, needed by a map with context, is a traced setting)."""
    if config.context and context_scaling is None:
        context_scaling = ContextScaling(*(jnp.zeros(context_size(config.state_dim, config.observation_dim)),) * 2)
    settings, structure = recipe(
        num_iterations=max(num_iterations, 1), batch_size=config.batch_size, inner_steps=config.inner_steps,
        width=config.width, num_blocks=config.num_blocks, activation=config.activation,
        enkf_layer=config.enkf_layer, potential_optimizer=None, transport_optimizer=None, warm_start=True,
        divergence_threshold=10.0, trend_threshold=10.0, inflation=config.inflation, concavity_points=0,
        concavity_step=0.1, prior_smoothing=0.0, fresh_observations=True,
        potential_learning_rate=config.potential_learning_rate,
        potential_weight_decay=config.potential_weight_decay,
        transport_learning_rate=config.transport_learning_rate,
    )
    return (settings._replace(context_scaling=context_scaling if config.context else None),
            structure._replace(contextual=bool(config.context)))


def collect_forecasts(key: Array, model: StateSpaceModel, update, *, num_simulations: int, num_steps: int,
                      num_particles: int, burn_in: int = 0, inflation=1.0) -> ForecastBank:
    """Forecast ensembles of ``update``'s filter on ``num_simulations`` simulated trajectories of
    ``num_steps`` (the first ``burn_in`` steps dropped), ordered by simulation."""
    truth_key, filter_key, bank_key = jax.random.split(key, 3)
    observations = _simulate_observations(truth_key, model, num_steps, num_simulations)
    analyses = _analyses(filter_key, model, update, observations, num_particles)
    return forecast_bank(bank_key, model, analyses[:, burn_in:], inflation)


@partial(jax.jit, static_argnums=(2, 3))
def _simulate_observations(key, model, num_steps, num_simulations):
    return jax.vmap(lambda k: simulate(k, model, num_steps)[1])(jax.random.split(key, num_simulations))


@partial(jax.jit, static_argnums=(4,))
def _analyses(key, model, update, observations, num_particles):
    keys = jax.random.split(key, observations.shape[0])
    return jax.vmap(lambda k, ys: run_filter(k, model, update, ys, num_particles).particles)(keys, observations)


def train_map(key: Array, model: StateSpaceModel, bank: ForecastBank, validation: ForecastBank, *,
              model_name: str, num_iterations: int = 20_000, batch_size: int = 256,
              ensembles_per_batch: int = 8, width: int = 64, num_blocks: int = 1, activation: str = "relu",
              enkf_layer: bool = False, inner_steps: int = 10, potential_learning_rate: float = 1e-4,
              potential_weight_decay: float = 1.0, transport_learning_rate: float = 1e-3,
              inflation: float = 1.0, context: bool = True, chunks: int = 20, validation_batches: int = 8,
              start: AmortisedMap | None = None) -> tuple[AmortisedMap, TrainingHistory]:
    """Trains a conditional map on the bank's ensembles: ``num_iterations`` outer iterations (one
    f step, ``inner_steps`` T steps) in ``chunks`` compiled chunks, reporting progress to
    ``ot_filter.progress`` listeners and the validation loss after each; from ``start``'s
    parameters (and context scaling) if given (its networks must match). ``context``: the
    networks also read each prior's context features, normalised by their statistics over the
    training ensembles."""
    n, m = bank.particles.shape[2], bank.scaling.y_mean.shape[1]
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    chunks = check_int("chunks", chunks)
    num_iterations = check_int("num_iterations", num_iterations, minimum=chunks)
    ensembles_per_batch = check_int("ensembles_per_batch", ensembles_per_batch)
    if check_int("batch_size", batch_size, minimum=2) % ensembles_per_batch or batch_size // ensembles_per_batch < 2:
        raise ValueError(f"batch_size = {batch_size} must be a multiple (>= 2x) of ensembles_per_batch = "
                         f"{ensembles_per_batch}")
    config = MapConfig(
        model=str(model_name), state_dim=int(n), observation_dim=int(m), width=check_int("width", width),
        num_blocks=check_int("num_blocks", num_blocks, minimum=0), activation=activation, enkf_layer=bool(enkf_layer),
        inner_steps=check_int("inner_steps", inner_steps), batch_size=int(batch_size),
        potential_learning_rate=float(check_number("potential_learning_rate", potential_learning_rate, 0.0, strict_minimum=True)),
        potential_weight_decay=float(check_number("potential_weight_decay", potential_weight_decay, 0.0)),
        transport_learning_rate=float(check_number("transport_learning_rate", transport_learning_rate, 0.0, strict_minimum=True)),
        inflation=float(check_number("inflation", inflation, 1.0)), context=bool(context),
    )
    context_scaling = fit_context_scaling(bank.context) if context else None
    if start is not None and context:
        context_scaling = start.context_scaling  # the networks learnt these inputs
    settings, structure = map_recipe(config, context_scaling=context_scaling)
    init_key, train_key, validation_key = jax.random.split(key, 3)
    dtype = bank.particles.dtype
    training = init_training(settings, structure, init_key, n, m, dtype)
    if start is not None:
        if _network_fields(start.config) != _network_fields(config):
            raise ValueError("start's networks differ from the ones asked for: "
                             f"{_network_fields(start.config)} vs {_network_fields(config)}")
        potential_optimizer, transport_optimizer = optimizers(settings, structure)
        training = TrainingState(start.params, potential_optimizer.init(start.params.potential),
                                 transport_optimizer.init(start.params.transport))
    per_chunk = num_iterations // chunks
    iterations, training_loss, validation_loss = [], [], []
    started = time.perf_counter()
    for chunk in range(chunks):
        training, smoothed = _train_chunk(jax.random.fold_in(train_key, chunk), training, model, bank, settings,
                                          structure, per_chunk, ensembles_per_batch)
        value = _validate(validation_key, training.params, model, validation, settings, structure,
                          ensembles_per_batch, validation_batches)
        iterations.append((chunk + 1) * per_chunk)
        training_loss.append(float(smoothed))
        validation_loss.append(float(value))
        report(chunk + 1, chunks)
    history = TrainingHistory(np.array(iterations), np.array(training_loss), np.array(validation_loss),
                              time.perf_counter() - started)
    info = {"iterations": int(iterations[-1]), "ensembles": int(bank.num_ensembles),
            "validation_ensembles": int(validation.num_ensembles), "seconds": history.seconds,
            "final_validation_loss": validation_loss[-1], "finite": bool(np.isfinite(validation_loss[-1]))}
    return AmortisedMap(training.params, context_scaling, config, info), history


def _network_fields(config: MapConfig):
    return (config.state_dim, config.observation_dim, config.width, config.num_blocks, config.activation,
            config.enkf_layer, config.context)


@partial(jax.jit, static_argnames=("structure", "num_iterations", "ensembles_per_batch"))
def _train_chunk(key, training, model, bank, settings, structure, num_iterations, ensembles_per_batch):
    potential_net, transport_net = networks(structure)
    potential_optimizer, transport_optimizer = optimizers(settings, structure)
    training, trace = train_saddle(
        key, training,
        lambda batch_key: bank_batch(batch_key, bank, model.sample_observation, batch_size=structure.batch_size,
                                     ensembles_per_batch=ensembles_per_batch, enkf_layer=structure.enkf_layer,
                                     context_scaling=settings.context_scaling),
        num_iterations, potential_net=potential_net, transport_net=transport_net,
        potential_optimizer=potential_optimizer, transport_optimizer=transport_optimizer,
        inner_steps=structure.inner_steps, enkf_layer=structure.enkf_layer, record_length=1,
    )
    return training, jnp.where(trace.finite, trace.smoothed_loss, jnp.inf)


@partial(jax.jit, static_argnames=("structure", "ensembles_per_batch", "num_batches"))
def _validate(key, params, model, bank, settings, structure, ensembles_per_batch, num_batches):
    """Mean J of fixed parameters on ``num_batches`` mini-batches of held-out ensembles (the same
    batches at every call: the key is fixed)."""
    potential_net, transport_net = networks(structure)

    def one(batch_key):
        return evaluate_saddle(
            batch_key, params,
            lambda k: bank_batch(k, bank, model.sample_observation, batch_size=structure.batch_size,
                                 ensembles_per_batch=ensembles_per_batch, enkf_layer=structure.enkf_layer,
                                 context_scaling=settings.context_scaling),
            potential_net=potential_net, transport_net=transport_net, enkf_layer=structure.enkf_layer,
        )

    return jnp.mean(jax.vmap(one)(jax.random.split(key, num_batches)))


def train_amortised(key: Array, model: StateSpaceModel, *, model_name: str, num_simulations: int,
                    num_steps: int, num_particles: int, burn_in: int = 0, rounds: int = 2,
                    validation_fraction: float = 0.2, num_iterations: int = 20_000, first_update=None,
                    **options: Any) -> tuple[AmortisedMap, list[TrainingHistory]]:
    """Offline training in ``rounds``: the first on the forecasts of ``first_update``'s filter
    (default: the perturbed-observation EnKF), each later one, warm-started, on the forecasts of
    the amortised filter with the map so far (``num_iterations`` split evenly over the rounds).
    The last ``validation_fraction`` of the simulations are held out. ``options``: ``train_map``'s
    network and optimiser settings."""
    from ot_filter.updates.amortised import amortised_ot  # the update builder uses this module
    from ot_filter.updates.enkf import enkf

    rounds = check_int("rounds", rounds)
    update = first_update if first_update is not None else enkf()
    trained, histories = None, []
    started = time.perf_counter()
    for index in range(rounds):
        round_key = jax.random.fold_in(key, index)
        collect_key, train_key = jax.random.split(round_key)
        bank = collect_forecasts(collect_key, model, update, num_simulations=num_simulations, num_steps=num_steps,
                                 num_particles=num_particles, burn_in=burn_in,
                                 inflation=options.get("inflation", 1.0))
        training_bank, validation = split_bank(bank, validation_fraction)
        trained, history = train_map(train_key, model, training_bank, validation, model_name=model_name,
                                     num_iterations=num_iterations // rounds, start=trained, **options)
        histories.append(history)
        update = amortised_ot(trained)
    info = dict(trained.info, rounds=rounds, iterations=int(sum(h.iterations[-1] for h in histories)),
                seconds=time.perf_counter() - started, simulations=num_simulations, steps=num_steps,
                particles=num_particles, burn_in=burn_in)
    return trained._replace(info=info), histories
