"""Cost of the in-scan progress reports (``progress=k``, about 20 reports a run) against none.

    PYTHONPATH=. python benchmarks/progress_overhead.py [--repeats 15]

Each filter is compiled with and without reports, then both are timed alternately ``--repeats``
times (after compilation); the overhead is the ratio of the medians minus one. A listener that
does nothing but count is registered, as a progress bar would be. Cases: the cheapest filters
per step (where a fixed per-report cost weighs most): the Lorenz-63 twin with the square-root
EnKF (N = 10, 1001 analyses of 25 RK4 steps), Lorenz-96 with the EnKF (n = 40, N = 40, 1001
steps), and the FPF with the constant gain (Ornstein-Uhlenbeck, N = 1000, 2000 steps); and two
long filters, the ones progress reports are for: the OT filter on Lorenz-63 (N = 200, 100 steps)
and the kernel-gain FPF on the bimodal example (N = 1000, 200 steps).
Writes benchmarks/results/progress_overhead.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import jax

import ot_filter as otf
from ot_filter import continuous as ct
from ot_filter.experiments._common import write_text_atomic
from ot_filter.progress import every_fraction, progress_listener


def cases():
    l63 = otf.models.lorenz63()
    _, y63 = otf.simulate(jax.random.key(0), l63, 1001)
    l96 = otf.models.lorenz96()
    _, y96 = otf.simulate(jax.random.key(0), l96, 1001)
    ou = ct.ornstein_uhlenbeck()
    path = ct.simulate_sde(jax.random.key(0), ou, 0.01, 2000)
    enkf = otf.enkf(inflation=1.02, perturbed=False, rotate=True)
    bimodal = ct.squared_observation_sde()
    bimodal_path = ct.simulate_sde(jax.random.key(0), bimodal, 0.01, 200)
    ot = otf.ot(num_iterations=(256, 32))
    return {
        "Lorenz-63, OT filter N=200, T=100": lambda k, p: otf.run_filter(k, l63, ot, y63[:100], 200, save_every=0, progress=p).mean,
        "FPF kernel gain N=1000, T=200": lambda k, p: ct.run_fpf(k, bimodal, ct.kernel_gain(0.1), bimodal_path.increments, 0.01, 1000, progress=p).mean,
        "Lorenz-63, EnKF N=10, T=1001": lambda k, p: otf.run_filter(k, l63, enkf, y63, 10, save_every=0, progress=p).mean,
        "Lorenz-96, EnKF N=40, T=1001": lambda k, p: otf.run_filter(k, l96, enkf, y96, 40, save_every=0, progress=p).mean,
        "FPF constant gain N=1000, T=2000": lambda k, p: ct.run_fpf(k, ou, ct.constant_gain(), path.increments, 0.01, 1000, progress=p).mean,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--out", default="benchmarks/results")
    args = parser.parse_args()
    reports = []
    rows = {}
    with progress_listener(lambda done, total: reports.append(done)):
        for name, run in cases().items():
            steps = int(name.rsplit("T=", 1)[1])
            every = every_fraction(steps)
            key = jax.random.key(1)
            for progress in (0, every):  # compile both
                jax.block_until_ready(run(key, progress))
            times = {0: [], every: []}
            for _ in range(args.repeats):
                for progress in (0, every):
                    start = time.perf_counter()
                    jax.block_until_ready(run(key, progress))
                    times[progress].append(time.perf_counter() - start)
            off, on = statistics.median(times[0]), statistics.median(times[every])
            rows[name] = {"seconds_off": off, "seconds_on": on, "overhead": on / off - 1,
                          "reports_per_run": -(-steps // every), "every": every}
            print(f"{name:36s} off {off * 1e3:8.2f} ms  on {on * 1e3:8.2f} ms  overhead {100 * (on / off - 1):+.1f} %"
                  f"  ({rows[name]['reports_per_run']} reports)")
    os.makedirs(args.out, exist_ok=True)
    result = {"device": str(jax.devices()[0]), "repeats": args.repeats, "cases": rows}
    write_text_atomic(os.path.join(args.out, "progress_overhead.json"), json.dumps(result, indent=2))
    lines = ["# In-scan progress reports: cost (benchmarks/progress_overhead.py)", "",
             f"device: {result['device']}; medians of {args.repeats} alternating runs after compilation", "",
             "| filter | off, ms | on, ms | overhead | reports per run |", "|--|--:|--:|--:|--:|"]
    for name, row in rows.items():
        lines.append(f"| {name} | {row['seconds_off'] * 1e3:.2f} | {row['seconds_on'] * 1e3:.2f} | "
                     f"{100 * row['overhead']:+.1f} % | {row['reports_per_run']} |")
    write_text_atomic(os.path.join(args.out, "progress_overhead.md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
