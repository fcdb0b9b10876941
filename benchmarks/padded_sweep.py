"""A particle-count sweep as one padded program vs one program per particle count.

Run (from the repository root):

    PYTHONPATH=. python benchmarks/padded_sweep.py              # about 1-2 minutes on 2 cores
    PYTHONPATH=. python benchmarks/padded_sweep.py --repeats 1  # a faster check

Problem: the squared-observation model ``ot_filter.models.squared_observation(dim=2)``, 20 time
steps, 20 simulations (truths and observations from ``ot_filter.simulate``), filtered by the
EnKF (``enkf()``, perturbed observations with the exact R) and SIR (``sir()``, systematic
resampling every step) with N in {100, 200, 400, 800, 1600} particles.

Two ways to run the sweep, both vmapped over the 20 simulations (``save_every=0``):

- per N: five jitted programs, one per particle count (N is static);
- padded: one jitted program with N_max = 1600 particles, vmapped over
  ``num_active`` in {100, ..., 1600} and over the simulations (a batch of 5 x 20 filters);
  padding is ignored by the updates (``ot_filter.updates.base``).

Measured: compile time (``jax.jit(f).lower(...).compile()``: tracing, lowering, XLA) and run time
(median over ``--repeats`` calls of the compiled program, ``block_until_ready``) of each
approach, and the time-averaged RMSE of the filter mean per N (mean over simulations). Since
``jax.random`` streams are prefix-consistent, the padded run with num_active = N uses the same
random numbers as the per-N run with the same key, so the two filter means agree: the EnKF's up
to float32 rounding; SIR's exactly, except where rounding (sums over 1600 entries instead of N)
moves a resampling point across a cumulative-weight boundary and that run then follows another
path. Reported: the largest difference of the means and, per N, the number of simulations whose
means differ by more than 1e-4.

The padded program does N_max work for every count (5 x 1600 particles per simulation against
100 + 200 + 400 + 800 + 1600 = 3100), so it trades run time for a single compilation; the batch
stays at 5 x 20 = 100 filters: jaxlib's CPU batched LAPACK calls under vmap of 128 or more
simulations deadlocked on this 2-core machine.

Output: a table on stdout and ``benchmarks/results/padded_sweep.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter

RESULTS = Path(__file__).resolve().parent / "results"
COUNTS = (100, 200, 400, 800, 1600)
NUM_STEPS = 20
NUM_SIMULATIONS = 20
TRUTH_SEED = 0
FILTER_SEED = 1
UPDATES = {"EnKF": ot_filter.enkf, "SIR": ot_filter.sir}


def timed_compile(function, *args):
    """(compiled, seconds) of tracing, lowering and compiling ``jax.jit(function)``."""
    start = time.perf_counter()
    compiled = jax.jit(function).lower(*args).compile()
    return compiled, time.perf_counter() - start


def timed_runs(compiled, args, repeats: int):
    """(output, median seconds) of ``repeats`` calls of a compiled program."""
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        output = jax.block_until_ready(compiled(*args))
        seconds.append(time.perf_counter() - start)
    return output, statistics.median(seconds)


def rmse(means, states):
    """Time-averaged RMSE of the filter means ``[..., S, T, n]``, averaged over simulations."""
    return np.asarray(ot_filter.metrics.rmse(means, states).mean(axis=(-1, -2)))


def measure(name: str, model, states, observations, repeats: int) -> dict:
    update = UPDATES[name]()
    keys = jax.random.split(jax.random.key(FILTER_SEED), NUM_SIMULATIONS)

    per_count = []
    per_count_means = []
    for num_particles in COUNTS:
        def sweep(keys, observations, num_particles=num_particles):
            return jax.vmap(lambda key, y: ot_filter.run_filter(
                key, model, update, y, num_particles, save_every=0).mean)(keys, observations)

        compiled, compile_seconds = timed_compile(sweep, keys, observations)
        means, run_seconds = timed_runs(compiled, (keys, observations), repeats)
        per_count_means.append(np.asarray(means))
        per_count.append({"num_particles": num_particles, "compile_seconds": compile_seconds,
                          "run_seconds": run_seconds, "rmse": float(rmse(means, states))})

    def padded_sweep(keys, observations, counts):
        def one_count(count):
            return jax.vmap(lambda key, y: ot_filter.run_filter(
                key, model, update, y, COUNTS[-1], save_every=0, num_active=count).mean)(
                keys, observations)

        return jax.vmap(one_count)(counts)

    counts = jnp.asarray(COUNTS)
    compiled, padded_compile = timed_compile(padded_sweep, keys, observations, counts)
    padded_means, padded_run = timed_runs(compiled, (keys, observations, counts), repeats)
    padded_means = np.asarray(padded_means)
    differences = [np.abs(padded_means[i] - per_count_means[i]) for i in range(len(COUNTS))]
    for row, difference in zip(per_count, differences):
        row["simulations_differing_from_padded"] = int(np.sum(difference.max(axis=(1, 2)) > 1e-4))
    return {
        "per_count": per_count,
        "per_count_total": {
            "compile_seconds": sum(row["compile_seconds"] for row in per_count),
            "run_seconds": sum(row["run_seconds"] for row in per_count),
        },
        "padded": {
            "num_particles": COUNTS[-1],
            "compile_seconds": padded_compile,
            "run_seconds": padded_run,
            "rmse": [float(value) for value in rmse(padded_means, states)],
        },
        "max_abs_difference_of_means": max(float(difference.max()) for difference in differences),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per program (median)")
    parser.add_argument("--output-dir", type=Path, default=RESULTS)
    args = parser.parse_args()

    started = time.perf_counter()
    load_at_start = os.getloadavg()
    model = ot_filter.models.squared_observation(dim=2)
    truth_keys = jax.random.split(jax.random.key(TRUTH_SEED), NUM_SIMULATIONS)
    states, observations = jax.jit(jax.vmap(
        lambda key: ot_filter.simulate(key, model, NUM_STEPS)))(truth_keys)

    results = {name: measure(name, model, states, observations, args.repeats) for name in UPDATES}
    report = {
        "meta": {
            "date": time.strftime("%Y-%m-%d %H:%M"),
            "command": "python " + " ".join(sys.argv),
            "platform": platform.platform(terse=True),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "jax": jax.__version__,
            "jax_device": jax.devices()[0].platform,
            "model": "squared_observation(dim=2)",
            "num_steps": NUM_STEPS,
            "num_simulations": NUM_SIMULATIONS,
            "counts": list(COUNTS),
            "repeats": args.repeats,
            "total_seconds": time.perf_counter() - started,
            # Other processes share the CPUs: timings are only comparable at a similar load.
            "load_average_1_5_15_min": {"start": load_at_start, "end": os.getloadavg()},
        },
        "results": results,
    }

    print(f"{NUM_SIMULATIONS} simulations x {NUM_STEPS} steps, N in {list(COUNTS)}; seconds")
    print(f"{'update':6} {'approach':22} {'compile':>8} {'run':>8}")
    for name, result in results.items():
        total = result["per_count_total"]
        print(f"{name:6} {'per N (5 programs)':22} {total['compile_seconds']:8.2f} {total['run_seconds']:8.3f}")
        padded = result["padded"]
        print(f"{name:6} {'padded (1 program)':22} {padded['compile_seconds']:8.2f} {padded['run_seconds']:8.3f}")
    for name, result in results.items():
        rows = ", ".join(f"N={row['num_particles']}: {row['compile_seconds']:.2f}/{row['run_seconds']:.3f}"
                         for row in result["per_count"])
        print(f"{name} per N compile/run: {rows}")
        rmses = ", ".join(f"{row['rmse']:.3f}" for row in result["per_count"])
        print(f"{name} RMSE per N: {rmses}; padded: "
              + ", ".join(f"{value:.3f}" for value in result["padded"]["rmse"])
              + f"; max |mean difference| {result['max_abs_difference_of_means']:.2e}, simulations"
              + " differing by > 1e-4 per N: "
              + str([row["simulations_differing_from_padded"] for row in result["per_count"]]))

    args.output_dir.mkdir(parents=True, exist_ok=True)
    (args.output_dir / "padded_sweep.json").write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
