"""The chapter's Lorenz-63 experiment, measured: MSE over time of EnKF, SIR and the OT filter.

    PYTHONPATH=. python benchmarks/lorenz63_chapter.py [--simulations 10] [--steps 500]
        [--methods enkf,sir,ot,ot_enkf] [--out benchmarks/results/lorenz63_chapter]

N = 1000 particles, components 1 and 3 observed (variance 10), 500 Euler steps of 0.01; the OT
filter with the authors' 1024 -> 64 iteration schedule, with and without the EnKF layer. Reports
per method: simulations whose MSE stays below 1 after t = 1.5, the MSE after t = 1.5, compile
seconds and seconds per filter step (all simulations vmapped in one program, sharded over one
single-threaded XLA device per CPU core unless --one-device). Writes
results.json, results.md and two PNGs to --out.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from ot_filter.experiments._common import host_devices_for_cpu_cores

if "--one-device" not in sys.argv:
    host_devices_for_cpu_cores()  # before JAX starts: simulations sharded over the CPU cores

import jax  # noqa: E402

from ot_filter.experiments._common import write_text_atomic  # noqa: E402
from ot_filter.experiments.lorenz63 import LABELS, plot_lorenz63, run_lorenz63  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--simulations", type=int, default=10)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--methods", default="enkf,sir,ot,ot_enkf")
    parser.add_argument("--reference", type=int, default=100_000, help="particles of the exact-Bayes SIR (0: none)")
    parser.add_argument("--out", default="benchmarks/results/lorenz63_chapter")
    parser.add_argument("--one-device", action="store_true",
                        help="one multi-threaded CPU device instead of one single-threaded device per core")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    start = time.perf_counter()
    result = run_lorenz63(jax.random.key(2026), num_particles=args.particles, num_steps=args.steps,
                          num_simulations=args.simulations, methods=args.methods.split(","),
                          reference_particles=args.reference)
    summary = result["metrics"]
    summary["wall_s"] = time.perf_counter() - start
    summary["device"] = f"{len(jax.devices())} x {jax.devices()[0]}"
    plot_lorenz63(result, args.out)
    lines = [f"# Lorenz-63 (chapter setting), N = {args.particles}, {args.simulations} simulations, "
             f"{args.steps} steps", "",
             "| method | sims with MSE < 1 at every t > 1.5 | sims with mean MSE over t > 1.5 below 1 | "
             "steps after 1.5 with MSE < 1 | MSE after t = 1.5 (mean +- s.e.) | "
             "max MSE after 1.5 (worst simulation) | compile s | run s (all simulations) | s per step (all sims) |",
             "|--|--:|--:|--:|--:|--:|--:|--:|--:|"]
    names = args.methods.split(",") + (["reference"] if args.reference else [])
    for name in names:
        r = summary[name]
        lines.append(f"| {LABELS[name]} | {r['settled_simulations']}/{args.simulations} | "
                     f"{r['settled_on_average_simulations']}/{args.simulations} | "
                     f"{100 * r['fraction_of_late_steps_below_target']:.0f}% | "
                     f"{r['mse_after_settle']['mean']:.3f} +- {r['mse_after_settle']['stderr']:.3f} | "
                     f"{max(r['max_mse_after_settle_per_simulation']):.3f} | {r['compile_s']:.1f} | "
                     f"{r['run_s']:.1f} | {r['seconds_per_step']:.4f} |")
        print(lines[-1], flush=True)
    lines.append(f"\nWall time including compilation and metrics: {summary['wall_s']:.0f} s on {summary['device']}.")
    print(lines[-1])
    write_text_atomic(os.path.join(args.out, "results.json"), json.dumps(summary, indent=1))
    write_text_atomic(os.path.join(args.out, "results.md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
