"""The chapter's dynamic example, measured: MMD over time, vs dimension and vs particle count.

    PYTHONPATH=. python benchmarks/dynamic_example.py [--simulations 20] [--parts time,dims,particles]
        [--sir-reference 100000] [--out benchmarks/results/dynamic_example]

- time: n = 2, N = 1000, 50 steps; MMD (h = 1) to the exact posterior over time and averaged over
  t in [1, 5]; also against a 10^5-particle SIR (the authors' reference) for comparison.
- dims: n in {2, 4, 6, 8, 10}, N = 1000, 20 steps; standardised MMD, h = 4.
- particles: N in {100, 200, 400, 800, 1600}, n = 2, 20 steps; standardised MMD, h = 0.6; one
  padded program per method (active-particle mask), and for comparison one program per N.
Writes results.json, results.md and PNGs to --out (each part as it finishes).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

from ot_filter.experiments._common import write_text_atomic
from ot_filter.experiments.dynamic_example import (
    plot_dynamic_example,
    plot_sweep,
    run_dimension_sweep,
    run_dynamic_example,
    run_particle_sweep,
)

KEY = 2026


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--simulations", type=int, default=20)
    parser.add_argument("--parts", default="time,dims,particles")
    parser.add_argument("--sir-reference", type=int, default=100_000)
    parser.add_argument("--out", default="benchmarks/results/dynamic_example")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "results.json")
    results = json.load(open(path)) if os.path.exists(path) else {}
    results["device"] = str(jax.devices()[0])
    parts = args.parts.split(",")
    key = jax.random.key(KEY)
    if "time" in parts:
        start = time.perf_counter()
        result = run_dynamic_example(key, num_simulations=args.simulations, sir_reference=args.sir_reference)
        result["metrics"]["wall_s"] = time.perf_counter() - start
        plot_dynamic_example(result, args.out)
        results["time"] = result["metrics"]
        _write(args.out, results)
        _print_time(result["metrics"])
    if "dims" in parts:
        start = time.perf_counter()
        result = run_dimension_sweep(key, num_simulations=args.simulations)
        result["metrics"]["wall_s"] = time.perf_counter() - start
        plot_sweep(result, args.out)
        results["dims"] = result["metrics"]
        _write(args.out, results)
        _print_sweep(result["metrics"], "dims")
    if "particles" in parts:
        for padded in (True, False):
            start = time.perf_counter()
            result = run_particle_sweep(key, num_simulations=args.simulations, padded=padded)
            result["metrics"]["wall_s"] = time.perf_counter() - start
            name = "particles" if padded else "particles_one_program_per_count"
            if padded:
                plot_sweep(result, args.out)
            results[name] = result["metrics"]
            _write(args.out, results)
            _print_sweep(result["metrics"], "counts")


def _print_time(m):
    for name in ("enkf", "sir", "ot"):
        r = m[name]
        print(f"{name}: MMD avg t>=1 {r['mmd_average']['mean']:.3f} +- {r['mmd_average']['stderr']:.3f}, "
              f"mode imbalance {r['mode_imbalance']:.3f}, compile {r['compile_s']:.1f} s, run {r['run_s']:.1f} s "
              f"({1e3 * r['seconds_per_step']:.2f} ms per step and simulation)", flush=True)
    if "sir_reference" in m:
        ref = m["sir_reference"]
        print("vs 1e5 SIR: " + ", ".join(f"{n} {ref[n]['mmd_average']['mean']:.3f}" for n in ("enkf", "sir", "ot"))
              + f"; its mode imbalance {ref['mode_imbalance']:.3f} (max {ref['max_mode_imbalance']:.3f})")
    print(f"OT best in {m.get('ot_best_simulations')}/{m['num_simulations']} simulations; wall {m['wall_s']:.0f} s")


def _print_sweep(m, axis):
    for x in m[axis]:
        row = m["results"][str(x)]
        print(f"{axis[:-1]} {x}: " + ", ".join(
            f"{n} {row[n]['mmd_average']['mean']:.3f}+-{row[n]['mmd_average']['stderr']:.3f}" for n in row), flush=True)
    if "timing" in m:
        print("timing: " + json.dumps(m["timing"]))
    print(f"wall {m['wall_s']:.0f} s", flush=True)


def _write(out, results):
    write_text_atomic(os.path.join(out, "results.json"), json.dumps(results, indent=1))
    lines = ["# Dynamic example (MMD to the exact posterior; mean +- s.e. over simulations)", ""]
    if "time" in results:
        m = results["time"]
        lines += [f"## MMD over time (n = {m['dim']}, N = {m['num_particles']}, {m['num_simulations']} simulations, "
                  f"h = {m['bandwidth']}, average over t >= {m['average_from']})", "",
                  "| method | exact reference | 10^5-SIR reference | published (SIR ref.) | mode imbalance | compile s | s per step and simulation |",
                  "|--|--:|--:|--:|--:|--:|--:|"]
        for name in ("enkf", "sir", "ot"):
            r = m[name]
            ref = m.get("sir_reference", {}).get(name, {}).get("mmd_average", {}).get("mean", float("nan"))
            lines.append(f"| {name} | {r['mmd_average']['mean']:.3f} +- {r['mmd_average']['stderr']:.3f} | {ref:.3f} | "
                         f"{m['published'][name]} | {r['mode_imbalance']:.3f} | {r['compile_s']:.1f} | "
                         f"{r['seconds_per_step']:.2e} |")
        if "sir_reference" in m:
            lines.append(f"\n10^5-particle SIR reference: mass on the positive side off 1/2 by "
                         f"{m['sir_reference']['mode_imbalance']:.3f} on average (max {m['sir_reference']['max_mode_imbalance']:.3f}); "
                         f"exact reference: {m['reference_mode_imbalance']:.1e}.")
    for part, axis, title in (("dims", "dims", "MMD vs dimension n"), ("particles", "counts", "MMD vs particle count N"),
                              ("particles_one_program_per_count", "counts", "MMD vs N, one program per N")):
        if part not in results:
            continue
        m = results[part]
        methods = list(m["results"][str(m[axis][0])])
        lines += ["", f"## {title} ({m['num_simulations']} simulations, standardised, h = {m['bandwidth']})", "",
                  "| " + axis[:-1] + " | " + " | ".join(methods) + " | published OT | published SIR |",
                  "|--:|" + "--:|" * (len(methods) + 2)]
        for i, x in enumerate(m[axis]):
            row = m["results"][str(x)]
            lines.append(f"| {x} | " + " | ".join(
                f"{row[n]['mmd_average']['mean']:.3f} +- {row[n]['mmd_average']['stderr']:.3f}" for n in methods)
                + f" | {m['published']['ot'][i]} | {m['published']['sir'][i]} |")
        if "timing" in m:
            lines.append("\nCompile / run seconds per method: " + ", ".join(
                f"{n} {t['compile_s']:.1f} / {t['run_s']:.1f}" for n, t in m["timing"].items()))
    write_text_atomic(os.path.join(out, "results.md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
