"""The localised OT filter with a map trained offline, on the chapter's dynamic example.

The coordinates are independent and observed one by one (windows of radius 0), so every
coordinate's local problem at every step is one of a single family, which one shared map can
learn offline (``amortised.local``). Offline: the online localised filter's forecasts on
simulated truths of the filter's model (the bank; the last fifth of its simulations held out for
the validation loss), and the shared map trained on their local pairs. Online:

- ``local_amortised`` (a): the map as is, one forward pass a step;
- ``local_amortised_warm`` (b): ``WARM_ITERATIONS`` iterations a step with ``WARM_OPTIONS``
  (batches of 128, the online filter's before 0.2.19, and ``local_ot``'s default f rate), each
  step from the map (fresh optimiser states).

Measured with ``benchmarks/local_amortised_dynamic.py`` (N = 1000, 10 simulations, W1 per
coordinate to the exact filter, floor 0.033-0.034; docs/amortised.md, "The localised update with a map
trained offline"): n = 10, bank of 400 ensembles: (a) 0.130, (b) 0.090, the online localised
filter 0.138; n = 50, bank of 80: (a) 0.105, (b) 0.093, online 0.145. With a bank of 80 at
n = 10 (a) was 0.273: what the map needs is local problems, about 4,000 (``bank_simulations``).
"""

from __future__ import annotations

import math
import os
import time

import jax
import numpy as np

from ot_filter.amortised import (
    LocalMap,
    LocalMapConfig,
    TrainingHistory,
    amortised_local_ot,
    collect_forecasts,
    load_local_map,
    save_local_map,
    train_local_amortised,
)
from ot_filter.experiments.amortised import history_arrays
from ot_filter.lib.validation import check_int

# The map: width 64 (the online filter's), batches of 512 local pairs, f's rate 3e-4 (the
# measured settings above), no location context (it did not help on Lorenz-96).
LOCAL_MAP = {"width": 64, "batch_size": 512, "potential_learning_rate": 3e-4}
NUM_ITERATIONS = 20_000
# Local problems (ensembles x coordinates) the bank's training part should hold, and the most
# simulations it may take to get them (the bank is the online filter's forecasts: its cost, about
# 4.6 s a simulation of 20 steps on 2 cores). At n = 2 (through the runner, 10 simulations, the
# online localised filter 0.105): 25 simulations (800 problems) gave (a) W1 0.177 and (b) 0.084
# in an offline stage of 243 s, 60 simulations (1,920) 0.136 and 0.078 in 393 s.
# The simulations are at least ``MIN_SIMULATIONS`` (400 training ensembles of 20 steps) whatever
# n: the ensembles' variety counts too. At n = 50 (runner, 10 simulations, online filter 0.139)
# 5 simulations, 4,000 local problems from 80 ensembles, gave (a) 0.258 and (b) 0.145 (and 0.105
# and 0.093 in another training on 80 ensembles, benchmarks/local_amortised_dynamic.py).
LOCAL_PROBLEMS = 4_000
MIN_SIMULATIONS, MAX_SIMULATIONS = 25, 60
VALIDATION_FRACTION = 0.2
# (b): as measured above, batches of 128 local pairs and f's rate 1e-4. Through the runner at
# n = 10 (10 simulations) with the offline training's batch of 512 and rate 3e-4: W1 0.093 at 1.9
# times the online filter's time; batch 128 and rate 3e-4: 0.125 (f's faster steps on smaller
# batches pull the map away from the offline one).
WARM_ITERATIONS = 64
WARM_OPTIONS = {"batch_size": 128, "potential_learning_rate": 1e-4}
ONLINE_BATCH = 128  # the online filter whose forecasts make the bank (local_ot's default until 0.2.19)
METHODS = ("local_amortised", "local_amortised_warm")


def local_map_name(dim: int) -> str:
    """``dynamic-n10-local``: what a local map is trained for (checked at load)."""
    return f"dynamic-n{dim}-local"


def bank_simulations(dim: int, num_steps: int) -> int:
    """Simulations of the offline bank: enough for ``LOCAL_PROBLEMS`` local problems after the
    held-out fifth, at least ``MIN_SIMULATIONS``, at most ``MAX_SIMULATIONS`` (20 steps: n = 2,
    60 simulations; n >= 10, 25, 400 training ensembles)."""
    wanted = LOCAL_PROBLEMS / (dim * num_steps * (1 - VALIDATION_FRACTION))
    return int(min(MAX_SIMULATIONS, max(MIN_SIMULATIONS, math.ceil(wanted))))


def local_map_config(dim: int) -> LocalMapConfig:
    return LocalMapConfig(local_map_name(dim), dim, dim, radius=0.0, **LOCAL_MAP)


def train_local_dynamic_map(key: jax.Array, dim: int, num_particles: int = 1000, num_steps: int = 20,
                            num_iterations: int = NUM_ITERATIONS) -> tuple[LocalMap, TrainingHistory]:
    """The offline stage (module docstring): the bank, then the map. ``info`` records the bank's
    simulations and seconds and the whole stage's seconds."""
    from ot_filter.experiments._common import make_updates
    from ot_filter.experiments.dynamic_example import OT_FILTER_OPTIONS, dynamic_model

    model = dynamic_model(check_int("dim", dim))
    # The bank's online filter keeps the batches of 128 its maps were measured with (local_ot's
    # default is 512 since 0.2.19; not measured here).
    online = make_updates(("local_ot",), {"batch_size": ONLINE_BATCH}, OT_FILTER_OPTIONS, model=model,
                          radius=0.0)["local_ot"]
    simulations = bank_simulations(dim, num_steps)
    bank_key, train_key = jax.random.split(key)
    started = time.perf_counter()
    forecasts = jax.block_until_ready(collect_forecasts(bank_key, model, online, num_simulations=simulations,
                                                        num_steps=num_steps, num_particles=num_particles).particles)
    bank_seconds = time.perf_counter() - started
    local_map, history = train_local_amortised(train_key, model, local_map_config(dim), forecasts, num_iterations,
                                               validation_fraction=VALIDATION_FRACTION)
    info = dict(local_map.info, simulations=simulations, steps=num_steps, bank_seconds=bank_seconds,
                offline_seconds=time.perf_counter() - started)
    return local_map._replace(info=info), history


def local_map_for(directory: str, key: jax.Array, dim: int, num_particles: int = 1000, num_steps: int = 20,
                  num_iterations: int = NUM_ITERATIONS) -> tuple[LocalMap, TrainingHistory | None]:
    """The local map stored in ``directory`` (checked against the model and n), else one
    trained (``train_local_dynamic_map``) and stored there with its curves (``history.npz``)
    for later cells and runs. History: None when the map was reloaded."""
    if os.path.exists(os.path.join(directory, "map.json")):
        return load_local_map(directory, model=local_map_name(dim), state_dim=dim), None
    local_map, history = train_local_dynamic_map(key, dim, num_particles, num_steps, num_iterations)
    save_local_map(directory, local_map)
    np.savez(os.path.join(directory, "history.npz"), **history_arrays([history]))
    return local_map, history


def local_amortised_updates(local_map: LocalMap, dim: int) -> dict:
    """``{"local_amortised": (a), "local_amortised_warm": (b)}`` on the dynamic model of ``dim``."""
    from ot_filter.experiments.dynamic_example import dynamic_model

    model = dynamic_model(dim)
    return {"local_amortised": amortised_local_ot(local_map, model),
            "local_amortised_warm": amortised_local_ot(local_map, model, WARM_ITERATIONS, **WARM_OPTIONS)}
