"""The amortised filter's per-step cost without online training ((a)) against the EnKF's
(issue 18: at most 3x), on the stored maps of ``benchmarks/amortised_ot.py`` and the width-32
map of ``benchmarks/amortised_seeds.py``.

    PYTHONPATH=. python benchmarks/amortised_cost.py [--rounds 8] [--simulations 10]
        [--out benchmarks/results/amortised_ot/cost.json]

Each filter runs N = 1000 particles on the same simulated truths, vmapped over the simulations,
one jitted program per filter. The EnKF's step is a fraction of a millisecond, too short for one
timed run to measure: the filters of one experiment are timed in turn, ``--rounds`` times, and
each keeps its best run. Ratios are within one experiment of one process. Pin it to one core for
a quiet measurement (``taskset -c 0``).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

from ot_filter.amortised import load_map  # noqa: E402
from ot_filter.experiments._common import write_text_atomic  # noqa: E402
from ot_filter.experiments.amortised import experiment_model  # noqa: E402
from ot_filter.filtering import run_filter  # noqa: E402
from ot_filter.model import simulate  # noqa: E402
from ot_filter.updates.amortised import amortised_ot  # noqa: E402
from ot_filter.updates.enkf import enkf  # noqa: E402

MAPS = "benchmarks/results/amortised_ot/"
# (experiment, model arguments, steps, {label: stored map})
CASES = [
    ("dynamic n = 2", ("dynamic", dict(dim=2)), 20,
     {"(a), width 64 (the table's map)": "maps/dynamic-n2", "(a), width 32 (seed 0)": "seeds/maps/width32-seed0"}),
    ("dynamic n = 10", ("dynamic", dict(dim=10)), 20, {"(a), width 64 (the table's map)": "maps/dynamic-n10"}),
    ("Lorenz-63, observed 1,3", ("lorenz63", dict(observed=(0, 2))), 100,
     {"(a) (the table's map)": "maps/lorenz63-obs0,2"}),
    ("Lorenz-63, observed 1", ("lorenz63", dict(observed=(0,))), 100,
     {"(a) (the table's map)": "maps/lorenz63-obs0"}),
]


def measure(model, updates, num_steps, num_simulations, num_particles, rounds):
    """Best run seconds per step and simulation of each update, timed in turn ``rounds`` times."""
    keys = jax.random.split(jax.random.key(0), num_simulations)
    observations = jax.vmap(lambda k: simulate(k, model, num_steps)[1])(jax.random.split(jax.random.key(1),
                                                                                          num_simulations))
    programs = {name: jax.jit(jax.vmap(lambda k, y, u=update: run_filter(k, model, u, y, num_particles).mean))
                for name, update in updates.items()}
    for program in programs.values():
        jax.block_until_ready(program(keys, observations))
    best = {name: float("inf") for name in programs}
    for _ in range(rounds):
        for name, program in programs.items():
            started = time.perf_counter()
            jax.block_until_ready(program(keys, observations))
            best[name] = min(best[name], time.perf_counter() - started)
    return {name: seconds / (num_steps * num_simulations) for name, seconds in best.items()}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--simulations", type=int, default=10)
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--out", default=os.path.join(MAPS, "cost.json"))
    args = parser.parse_args()
    records = []
    for experiment, (name, model_args), num_steps, maps in CASES:
        updates = {"EnKF": enkf(), **{label: amortised_ot(load_map(os.path.join(MAPS, path)))
                                     for label, path in maps.items()}}
        seconds = measure(experiment_model(name, **model_args), updates, num_steps, args.simulations,
                          args.particles, args.rounds)
        for label, value in seconds.items():
            records.append({"experiment": experiment, "filter": label, "ms_per_step": value * 1e3,
                            "vs_enkf": value / seconds["EnKF"]})
            print(f"{experiment}: {label}: {value * 1e3:.3f} ms a step ({value / seconds['EnKF']:.2f}x the EnKF)",
                  flush=True)
    write_text_atomic(args.out, json.dumps({"particles": args.particles, "simulations": args.simulations,
                                            "rounds": args.rounds, "records": records}, indent=1))


if __name__ == "__main__":
    main()
