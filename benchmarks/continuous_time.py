"""Continuous time, measured: the bimodal example (FPF gains vs the exact posterior) and the
seconds per time step of each gain.

    PYTHONPATH=. python benchmarks/continuous_time.py [--parts bimodal,speed] [--simulations 4]
        [--quick] [--out benchmarks/results/continuous_time]

- bimodal: dY = X^2 dt + dW, static X ~ N(0, 1), truth X = 1, dt = 0.01, 200 steps, N = 1000;
  MMD (h = 0.5) of each FPF gain's ensemble to the exact posterior over time; a 10^5-particle SIR
  on the discretised model checked against the exact posterior too.
- speed: Lorenz-63 with continuous observation of all components (n = m = 3), N = 10^3 and 10^4;
  seconds per FPF time step for each gain, steady state: (time of 1 + k steps - time of 1 step) / k
  (k = 5; 500 for the constant gain, whose step is too short to time over 5), each compiled
  beforehand (compile seconds reported separately). ``--gains`` times a subset and keeps the
  other rows of an existing results.json.
Writes results.json, results.md and PNGs to --out.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from ot_filter import continuous as ct
from ot_filter.experiments._common import write_text_atomic
from ot_filter.experiments.continuous_time import plot_bimodal_example, run_bimodal_example

SPEED_GAINS = {  # name: (builder, extra steps timed after the first)
    "constant": (lambda: ct.constant_gain(), 500),  # ~0.1 ms a step: time many to beat the noise
    "kernel (eps 1)": (lambda: ct.kernel_gain(1.0), 5),
    "learned (full batch)": (lambda: ct.learned_gain(), 5),
    "learned (batch 256)": (lambda: ct.learned_gain(batch_size=256), 5),
}


def time_gain(gain, num_particles: int, dt: float = 0.01, extra_steps: int = 5) -> dict:
    model = ct.lorenz63_sde()
    increments = ct.simulate_sde(jax.random.key(0), model, dt, 1 + extra_steps).increments
    timings = {}
    for steps in (1, 1 + extra_steps):
        run = jax.jit(lambda key, inc: ct.run_fpf(key, model, gain, inc, dt, num_particles).mean)
        start = time.perf_counter()
        compiled = run.lower(jax.random.key(1), increments[:steps]).compile()
        compile_s = time.perf_counter() - start
        start = time.perf_counter()
        mean = jax.block_until_ready(compiled(jax.random.key(1), increments[:steps]))
        timings[steps] = time.perf_counter() - start
        finite = bool(np.all(np.isfinite(np.asarray(mean))))
    return {
        "compile_s": compile_s,
        "first_step_s": timings[1],
        "seconds_per_step": (timings[1 + extra_steps] - timings[1]) / extra_steps,
        "finite": finite,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="bimodal,speed")
    parser.add_argument("--simulations", type=int, default=4)
    parser.add_argument("--quick", action="store_true", help="tiny settings (a smoke run)")
    parser.add_argument("--out", default="benchmarks/results/continuous_time")
    parser.add_argument("--gains", default=",".join(SPEED_GAINS), help="speed rows to (re)measure")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    results = {"device": str(jax.devices()[0])}
    existing = os.path.join(args.out, "results.json")
    if os.path.exists(existing):  # keep the parts and rows not rerun
        with open(existing) as stream:
            results.update({k: v for k, v in json.load(stream).items() if k != "device"})
    parts = args.parts.split(",")
    if "bimodal" in parts:
        options = dict(num_simulations=args.simulations)
        if args.quick:
            options.update(num_simulations=1, num_steps=50, num_particles=200, reference_particles=2000)
        start = time.perf_counter()
        metrics, arrays = run_bimodal_example(**options)
        metrics["wall_s"] = time.perf_counter() - start
        plot_bimodal_example(metrics, arrays, args.out)
        results["bimodal"] = metrics
        _write(args.out, results)
        for name, value in metrics["gains"].items():
            print(f"bimodal {name:9s} MMD (second half) {value['mmd_late']['mean']:.3f} +- "
                  f"{value['mmd_late']['stderr']:.3f}  positive mass {value['positive_mass_final']['mean']:.3f}  "
                  f"{value['seconds_per_step_and_simulation'] * 1e3:.1f} ms/step/sim  fallback steps "
                  f"{value['fallback_steps']}")
        print(f"bimodal 1e5-SIR vs exact: {metrics['sir_reference']['mmd_to_exact_final']['mean']:.4f}")
    if "speed" in parts:
        sizes = (200,) if args.quick else (1000, 10_000)
        speed = results.get("speed", {})
        for name, (build, extra_steps) in SPEED_GAINS.items():
            if name not in args.gains.split(","):
                continue
            for num in sizes:
                speed[f"{name}, N={num}"] = value = time_gain(build(), num, extra_steps=extra_steps)
                print(f"speed {name:22s} N={num:6d}: {value['seconds_per_step']:.4f} s/step "
                      f"(first step {value['first_step_s']:.2f} s, compile {value['compile_s']:.1f} s)")
                results["speed"] = speed
                _write(args.out, results)


def _write(out: str, results: dict) -> None:
    write_text_atomic(os.path.join(out, "results.json"), json.dumps(results, indent=2))
    lines = ["# Continuous time (benchmarks/continuous_time.py)", "", f"device: {results['device']}", ""]
    if "bimodal" in results:
        setting = results["bimodal"]["setting"]
        lines += [
            f"## Bimodal example: dY = X^2 dt + dW, X = {setting['true_state']}, dt = {setting['dt']}, "
            f"{setting['num_steps']} steps, N = {setting['num_particles']}, {setting['num_simulations']} simulations",
            "",
            "| gain | MMD to exact, second half (mean +- s.e.) | mass on x > 0 at the end (exact 0.5) | ms per step and simulation (after compilation) | fallback steps |",
            "|--|--:|--:|--:|--:|",
        ]
        for name, value in results["bimodal"]["gains"].items():
            lines.append(
                f"| {name} | {value['mmd_late']['mean']:.3f} +- {value['mmd_late']['stderr']:.3f} | "
                f"{value['positive_mass_final']['mean']:.3f} | {value['seconds_per_step_and_simulation'] * 1e3:.2f} | "
                f"{value['fallback_steps']} |"
            )
        reference = results["bimodal"]["sir_reference"]
        lines += ["", f"SIR with {reference['particles']} particles on the discretised model, MMD to the "
                      f"exact posterior at the end: {reference['mmd_to_exact_final']['mean']:.4f}", ""]
    if "speed" in results:
        lines += ["## Seconds per FPF time step, Lorenz-63 (n = m = 3)", "",
                  "| gain, N | s per step (steady) | first step s | compile s |", "|--|--:|--:|--:|"]
        for name, value in results["speed"].items():
            lines.append(f"| {name} | {value['seconds_per_step']:.3g} | {value['first_step_s']:.2f} | "
                         f"{value['compile_s']:.1f} |")
    write_text_atomic(os.path.join(out, "results.md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
