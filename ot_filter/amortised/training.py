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

Seeds: ``train_maps`` and ``train_amortised_seeds`` train S maps at once, one per key, their
training chunks and validations ``vmap``-ped over the seeds (one compiled program for all S);
each seed has its own bank (its own simulated trajectories, and in later rounds its own map's
forecasts), so that the spread over seeds is the whole offline procedure's. ``train_map`` and
``train_amortised`` are the same code with one seed.
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
           "stack_banks", "train_amortised", "train_amortised_seeds", "train_map", "train_maps"]


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
    last_iterate: SaddleParams | None = None  # where ``params`` is an average of iterates
    #   (``train_maps``' ``average_chunks``): the training's last iterate, the point the
    #   saddle-point game was at, from which warm-started online iterations may continue


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
              model_name: str, start: AmortisedMap | None = None, **options: Any) -> tuple[AmortisedMap, TrainingHistory]:
    """Trains one conditional map on the bank's ensembles (``train_maps`` with one seed; the
    options are its)."""
    maps, histories = train_maps(key[None], model, stack_banks([bank]), stack_banks([validation]),
                                 model_name=model_name, starts=None if start is None else [start], **options)
    return maps[0], histories[0]


def stack_banks(banks: list[ForecastBank]) -> ForecastBank:
    """One bank per seed, stacked along a new leading axis (they must hold as many ensembles)."""
    counts = {bank.num_ensembles for bank in banks}
    if len(counts) != 1:
        raise ValueError(f"the seeds' banks must hold as many ensembles, got {sorted(counts)}")
    return _stack(banks)


def _stack(trees: list) -> Any:
    """Pytrees of one structure, their leaves (arrays or Python numbers) stacked along a new
    leading axis."""
    return jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(leaf) for leaf in leaves]), *trees)


def train_maps(keys: Array, model: StateSpaceModel, banks: ForecastBank, validations: ForecastBank, *,
               model_name: str, num_iterations: int = 20_000, batch_size: int = 256,
               ensembles_per_batch: int = 8, width: int = 64, num_blocks: int = 1, activation: str = "relu",
               enkf_layer: bool = False, inner_steps: int = 10, potential_learning_rate: float = 1e-4,
               potential_weight_decay: float = 1.0, transport_learning_rate: float = 1e-3,
               inflation: float = 1.0, context: bool = True, chunks: int = 20, validation_batches: int = 8,
               average_chunks: int = 0, starts: list[AmortisedMap] | None = None,
               ) -> tuple[list[AmortisedMap], list[TrainingHistory]]:
    """Trains S conditional maps at once, map s from ``keys[s]`` on ``banks``' s-th bank
    (``stack_banks``; validation on ``validations``' s-th): ``num_iterations`` outer iterations
    (one f step, ``inner_steps`` T steps) in ``chunks`` compiled chunks, each ``vmap``-ped over
    the seeds, reporting progress to ``ot_filter.progress`` listeners and the validation loss
    after each; from ``starts[s]``'s parameters (and context scaling) if given (its networks must
    match). ``context``: the networks also read each prior's context features, normalised by
    their statistics over the seed's training ensembles.

    ``average_chunks`` k > 0: the map returned is the mean of the parameters at the ends of the
    last k chunks (an average of the iterates, as in Polyak averaging), not the last iterate.
    The saddle-point iterates wander around the solution, and the filter's error follows them:
    at n = 10 on the dynamic example, (a)'s W1 at the ends of 11 chunks of one round ranged from
    0.27 to 0.40, and the average of the round's 20 gave 0.22 and 0.28 (two trainings) against
    0.33 for their last iterates. The curves are the iterates'; ``info["final_validation_loss"]``
    is the returned map's. The last iterate is kept beside the average (``last_iterate``), and a
    next round (``starts``) continues from the average."""
    if keys.ndim != 1:
        raise ValueError(f"keys must be a 1-D array of PRNG keys (one per seed), got shape {keys.shape}")
    num_seeds = keys.shape[0]
    if banks.particles.ndim != 4 or banks.particles.shape[0] != num_seeds:
        raise ValueError(f"banks must be stacked per seed ([{num_seeds}, E, N, n], stack_banks), got particles of "
                         f"shape {banks.particles.shape}")
    if validations.particles.ndim != 4 or validations.particles.shape[0] != num_seeds:
        raise ValueError(f"validations must be stacked per seed ([{num_seeds}, E, N, n], stack_banks), got "
                         f"particles of shape {validations.particles.shape}")
    if starts is not None and len(starts) != num_seeds:
        raise ValueError(f"starts must hold one map per seed ({num_seeds}), got {len(starts)}")
    n, m = banks.particles.shape[3], banks.scaling.y_mean.shape[2]
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    chunks = check_int("chunks", chunks)
    average_chunks = check_int("average_chunks", average_chunks, minimum=0)
    if average_chunks > chunks:
        raise ValueError(f"average_chunks must be at most chunks = {chunks}, got {average_chunks}")
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
    if starts is not None:
        for start in starts:
            if _network_fields(start.config) != _network_fields(config):
                raise ValueError("start's networks differ from the ones asked for: "
                                 f"{_network_fields(start.config)} vs {_network_fields(config)}")
    seed_keys = jax.vmap(lambda k: jax.random.split(k, 3))(keys)  # [S, 3]: init, train, validation
    dtype = banks.particles.dtype
    per_seed_settings, per_seed_training = [], []
    for seed in range(num_seeds):
        start = None if starts is None else starts[seed]
        context_scaling = None
        if context:  # the networks learnt a start's inputs: keep its scaling
            context_scaling = (start.context_scaling if start is not None
                               else fit_context_scaling(banks.context[seed]))
        settings, structure = map_recipe(config, context_scaling=context_scaling)
        if start is None:
            training = init_training(settings, structure, seed_keys[seed, 0], n, m, dtype)
        else:
            potential_optimizer, transport_optimizer = optimizers(settings, structure)
            training = TrainingState(start.params, potential_optimizer.init(start.params.potential),
                                     transport_optimizer.init(start.params.transport))
        per_seed_settings.append(settings)
        per_seed_training.append(training)
    settings, training = _stack(per_seed_settings), _stack(per_seed_training)
    per_chunk = num_iterations // chunks
    iterations, training_loss, validation_loss = [], [], []
    summed = None  # the parameters summed over the averaged chunks
    started = time.perf_counter()
    for chunk in range(chunks):
        chunk_keys = jax.vmap(lambda k: jax.random.fold_in(k, chunk))(seed_keys[:, 1])
        training, smoothed = _train_chunk(chunk_keys, training, model, banks, settings, structure, per_chunk,
                                          ensembles_per_batch)
        if chunk >= chunks - average_chunks:
            summed = training.params if summed is None else jax.tree.map(jnp.add, summed, training.params)
        values = _validate(seed_keys[:, 2], training.params, model, validations, settings, structure,
                           ensembles_per_batch, validation_batches)
        iterations.append((chunk + 1) * per_chunk)
        training_loss.append(np.asarray(smoothed, float))
        validation_loss.append(np.asarray(values, float))
        report(chunk + 1, chunks)
    params, final_validation, last = training.params, validation_loss[-1], None
    if average_chunks:
        last = training.params
        params = jax.tree.map(lambda total: total / average_chunks, summed)
        final_validation = np.asarray(_validate(seed_keys[:, 2], params, model, validations, settings, structure,
                                                ensembles_per_batch, validation_batches), float)
    seconds = time.perf_counter() - started
    training_loss, validation_loss = np.stack(training_loss, axis=1), np.stack(validation_loss, axis=1)  # [S, C]
    maps, histories = [], []
    for seed in range(num_seeds):
        history = TrainingHistory(np.array(iterations), training_loss[seed], validation_loss[seed], seconds)
        info = {"iterations": int(iterations[-1]), "ensembles": int(banks.particles.shape[1]),
                "validation_ensembles": int(validations.particles.shape[1]), "seconds": seconds,
                "seeds_trained_together": num_seeds, "averaged_chunks": average_chunks,
                "final_validation_loss": float(final_validation[seed]),
                "finite": bool(np.isfinite(final_validation[seed]))}
        of_seed = lambda tree: None if tree is None else jax.tree.map(lambda leaf: leaf[seed], tree)  # noqa: E731
        maps.append(AmortisedMap(of_seed(params), per_seed_settings[seed].context_scaling, config, info,
                                 of_seed(last)))
        histories.append(history)
    return maps, histories


def _network_fields(config: MapConfig):
    return (config.state_dim, config.observation_dim, config.width, config.num_blocks, config.activation,
            config.enkf_layer, config.context)


@partial(jax.jit, static_argnames=("structure", "num_iterations", "ensembles_per_batch"))
def _train_chunk(keys, training, model, banks, settings, structure, num_iterations, ensembles_per_batch):
    """``num_iterations`` iterations of every seed (leading axis of all but model and structure)."""
    return jax.vmap(lambda *args: _train_one(*args, model, structure, num_iterations, ensembles_per_batch))(
        keys, training, banks, settings)


def _train_one(key, training, bank, settings, model, structure, num_iterations, ensembles_per_batch):
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
def _validate(keys, params, model, banks, settings, structure, ensembles_per_batch, num_batches):
    """Every seed's mean J of fixed parameters on ``num_batches`` mini-batches of its held-out
    ensembles (the same batches at every call: the keys are fixed)."""
    return jax.vmap(lambda *args: _validate_one(*args, model, structure, ensembles_per_batch, num_batches))(
        keys, params, banks, settings)


def _validate_one(key, params, bank, settings, model, structure, ensembles_per_batch, num_batches):
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
                    average_rounds: str = "every", **options: Any) -> tuple[AmortisedMap, list[TrainingHistory]]:
    """Offline training in ``rounds``: the first on the forecasts of ``first_update``'s filter
    (default: the perturbed-observation EnKF), each later one, warm-started, on the forecasts of
    the amortised filter with the map so far (``num_iterations`` split evenly over the rounds).
    The last ``validation_fraction`` of the simulations are held out. ``options``: ``train_map``'s
    network and optimiser settings; ``average_rounds``: ``train_amortised_seeds``'. Returns the
    map and one history per round."""
    maps, histories = train_amortised_seeds(
        key[None], model, model_name=model_name, num_simulations=num_simulations, num_steps=num_steps,
        num_particles=num_particles, burn_in=burn_in, rounds=rounds, validation_fraction=validation_fraction,
        num_iterations=num_iterations, first_update=first_update, average_rounds=average_rounds, **options)
    return maps[0], histories[0]


def train_amortised_seeds(keys: Array, model: StateSpaceModel, *, model_name: str, num_simulations: int,
                          num_steps: int, num_particles: int, burn_in: int = 0, rounds: int = 2,
                          validation_fraction: float = 0.2, num_iterations: int = 20_000, first_update=None,
                          average_rounds: str = "every", **options: Any,
                          ) -> tuple[list[AmortisedMap], list[list[TrainingHistory]]]:
    """``train_amortised`` for every key of ``keys`` ([S]) at once: seed s simulates its own
    trajectories (and, after the first round, its own map's forecasts); the training chunks of
    all seeds run as one ``vmap``-ped program (``train_maps``). Returns S maps and, per seed, one
    history per round.

    ``average_rounds`` (with ``train_maps``' ``average_chunks``): ``"every"`` round's map is the
    average of its iterates, and the next round's forecasts are that map's; ``"last"``: only the
    last round averages, so that the rounds before and the last iterate are the same as without
    averaging (the point (b)'s warm-started iterations start from), and only the map without
    online training (a) changes."""
    from ot_filter.updates.amortised import amortised_ot  # the update builder uses this module
    from ot_filter.updates.enkf import enkf

    rounds = check_int("rounds", rounds)
    if average_rounds not in ("every", "last"):
        raise ValueError(f"average_rounds must be 'every' or 'last', got {average_rounds!r}")
    if keys.ndim != 1:
        raise ValueError(f"keys must be a 1-D array of PRNG keys (one per seed), got shape {keys.shape}")
    num_seeds = keys.shape[0]
    updates = [first_update if first_update is not None else enkf()] * num_seeds
    trained, histories = None, []
    started = time.perf_counter()
    for index in range(rounds):
        round_keys = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, index)))(keys)  # [S, 2]
        banks = [collect_forecasts(round_keys[seed, 0], model, updates[seed], num_simulations=num_simulations,
                                   num_steps=num_steps, num_particles=num_particles, burn_in=burn_in,
                                   inflation=options.get("inflation", 1.0)) for seed in range(num_seeds)]
        splits = [split_bank(bank, validation_fraction) for bank in banks]
        del banks
        trained, round_histories = train_maps(
            round_keys[:, 1], model, stack_banks([training for training, _ in splits]),
            stack_banks([validation for _, validation in splits]), model_name=model_name,
            num_iterations=num_iterations // rounds, starts=trained,
            **(options if average_rounds == "every" or index == rounds - 1 else dict(options, average_chunks=0)))
        histories.append(round_histories)
        updates = [amortised_ot(one) for one in trained]
    seconds = time.perf_counter() - started
    maps = [one._replace(info=dict(one.info, rounds=rounds, iterations=int(sum(h[seed].iterations[-1]
                                                                                for h in histories)),
                                   seconds=seconds, simulations=num_simulations, steps=num_steps,
                                   particles=num_particles, burn_in=burn_in))
            for seed, one in enumerate(trained)]
    return maps, [[round_histories[seed] for round_histories in histories] for seed in range(num_seeds)]
