"""Scaling laws: time and memory of the analysis step and of whole filters vs N, n, and the OT
update's training cost vs mini-batch, width, n and N.

    PYTHONPATH=. python benchmarks/scaling.py [--parts particles,dimension,ot] [--quick]

- particles: Lorenz-63 (DAPPER's sakov2012 setting), SIR (systematic, ESS < 0.5 N) and EnKF
  (perturbed; square root) for N = 10^2 .. 10^6: seconds of one analysis step (``update.apply``
  on N particles, jit-compiled alone) and of a whole 20-cycle filter (``run_filter``,
  ``save_every=0``, 25 RK4 steps per cycle), and the compiled programs' memory (XLA's
  ``memory_analysis``: arguments + outputs + temporaries, the peak the program allocates).
  Fitted exponent b of time ~ N^b by least squares on log-log over N >= 10^4 (below that,
  fixed costs dominate) and over all N. At the smallest and largest N also the peak resident
  memory of a fresh process that compiles and runs the filter (``ru_maxrss``).
- dimension: Lorenz-96 (all observed, noise 1), EnKF square root N = 40 and perturbed N = 40,
  n = 40 .. 1000: one analysis step and a 20-cycle filter; fitted exponent in n.
- ot: the OT update's outer iterations per second (one f step and ``inner_steps`` T steps each)
  vs mini-batch (N = 10^4 fixed), vs width, vs n (static example, dim n), and vs N at a fixed
  mini-batch of 128 (N = 10^3 .. 10^5): the training cost must not grow with N; plus the
  compile time of the update.
Times: median of 5 calls after compilation (``block_until_ready``). Writes
benchmarks/results/scaling.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter as otf
from ot_filter.experiments._common import write_text_atomic


def timed(function, *args, repeats: int = 5) -> dict:
    start = time.perf_counter()
    compiled = jax.jit(function).lower(*args).compile()
    compile_s = time.perf_counter() - start
    memory = compiled.memory_analysis()
    peak = None
    if memory is not None:
        peak = int(memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes)
    jax.block_until_ready(compiled(*args))  # warm-up call, not timed
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - start)
    return {"seconds": statistics.median(times), "compile_s": compile_s, "memory_bytes": peak}


def exponent(xs, ys, minimum=0):
    pairs = [(x, y) for x, y in zip(xs, ys) if x >= minimum and y and y > 0]
    if len(pairs) < 2:
        return None
    logx, logy = np.log([p[0] for p in pairs]), np.log([p[1] for p in pairs])
    return float(np.polyfit(logx, logy, 1)[0])


PARTICLE_UPDATES = {
    "SIR (systematic, ESS < 0.5 N)": lambda: otf.sir(ess_threshold=0.5),
    "EnKF (perturbed)": lambda: otf.enkf(1.02),
    "EnKF (square root)": lambda: otf.enkf(1.02, perturbed=False),
}


def run_filter_once(name: str, num: int, cycles: int) -> None:
    """Child process: one whole Lorenz-63 filter (compile + run), then prints peak RSS in bytes."""
    model = otf.models.lorenz63()
    _, observations = otf.simulate(jax.random.key(0), model, cycles)
    update = PARTICLE_UPDATES[name]()
    mean = otf.run_filter(jax.random.key(3), model, update, observations, num, save_every=0).mean
    assert bool(jnp.all(jnp.isfinite(mean)))
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)  # Linux reports KiB


def peak_rss(name: str, num: int, cycles: int) -> int:
    """Peak resident memory of a fresh process that filters with N particles (JAX runtime and
    compilation included): what a user's process needs, beyond XLA's own allocation."""
    command = [sys.executable, os.path.abspath(__file__), "--rss-child", name, str(num), str(cycles)]
    completed = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=True)
    return int(completed.stdout.split()[-1])


def particle_scaling(counts, cycles: int = 20):
    model = otf.models.lorenz63()
    _, observations = otf.simulate(jax.random.key(0), model, cycles)
    updates = {name: make() for name, make in PARTICLE_UPDATES.items()}
    rows = {}
    for name, update in updates.items():
        rows[name] = []
        for num in counts:
            particles = jax.vmap(model.sample_initial)(jax.random.split(jax.random.key(1), num))

            def analysis(key, particles, update=update):
                state = update.init(key, particles, model)
                return update.apply(key, state, particles, observations[0], model)[0]

            def whole(key, update=update, num=num):
                return otf.run_filter(key, model, update, observations, num, save_every=0).mean

            one = timed(analysis, jax.random.key(2), particles)
            trajectory = timed(whole, jax.random.key(3), repeats=3)
            rows[name].append({"N": num, "analysis_s": one["seconds"], "analysis_memory_bytes": one["memory_bytes"],
                               "filter_s_per_cycle": trajectory["seconds"] / cycles,
                               "filter_memory_bytes": trajectory["memory_bytes"],
                               "filter_compile_s": trajectory["compile_s"]})
            print(f"{name:30s} N={num:8d} analysis {one['seconds'] * 1e3:9.3f} ms  cycle "
                  f"{trajectory['seconds'] / cycles * 1e3:9.3f} ms  memory {trajectory['memory_bytes'] / 2**20:8.1f} MiB",
                  flush=True)
    # Process peak RSS at the smallest and largest N (each in a fresh process).
    for name, row in rows.items():
        for entry in (row[0], row[-1]):
            entry["process_peak_rss_bytes"] = peak_rss(name, entry["N"], cycles)
            print(f"{name:30s} N={entry['N']:8d} process peak RSS "
                  f"{entry['process_peak_rss_bytes'] / 2**20:8.1f} MiB", flush=True)
    fits = {
        name: {
            "analysis_exponent_N>=1e4": exponent([r["N"] for r in row], [r["analysis_s"] for r in row], 10_000),
            "analysis_exponent_all": exponent([r["N"] for r in row], [r["analysis_s"] for r in row]),
            "cycle_exponent_N>=1e4": exponent([r["N"] for r in row], [r["filter_s_per_cycle"] for r in row], 10_000),
            "memory_exponent_N>=1e4": exponent([r["N"] for r in row], [r["filter_memory_bytes"] for r in row], 10_000),
        }
        for name, row in rows.items()
    }
    return {"cycles": cycles, "rows": rows, "fits": fits}


def dimension_scaling(dims, num_particles: int = 40, cycles: int = 20):
    rows = {}
    for name, update in {"EnKF (square root), N=40": otf.enkf(1.02, perturbed=False),
                         "EnKF (perturbed), N=40": otf.enkf(1.02)}.items():
        rows[name] = []
        for dim in dims:
            model = otf.models.lorenz96(dim=dim)
            _, observations = otf.simulate(jax.random.key(0), model, cycles)
            particles = jax.vmap(model.sample_initial)(jax.random.split(jax.random.key(1), num_particles))

            def analysis(key, particles, update=update, model=model, y=observations[0]):
                state = update.init(key, particles, model)
                return update.apply(key, state, particles, y, model)[0]

            def whole(key, update=update, model=model, observations=observations):
                return otf.run_filter(key, model, update, observations, num_particles, save_every=0).mean

            one = timed(analysis, jax.random.key(2), particles)
            trajectory = timed(whole, jax.random.key(3), repeats=3)
            rows[name].append({"n": dim, "analysis_s": one["seconds"], "filter_s_per_cycle": trajectory["seconds"] / cycles,
                               "filter_memory_bytes": trajectory["memory_bytes"]})
            print(f"{name:30s} n={dim:5d} analysis {one['seconds'] * 1e3:9.3f} ms  cycle "
                  f"{trajectory['seconds'] / cycles * 1e3:9.3f} ms", flush=True)
    fits = {name: {"analysis_exponent": exponent([r["n"] for r in row], [r["analysis_s"] for r in row], 100),
                   "cycle_exponent": exponent([r["n"] for r in row], [r["filter_s_per_cycle"] for r in row], 100)}
            for name, row in rows.items()}
    return {"cycles": cycles, "rows": rows, "fits": fits}


def ot_scaling(quick: bool):
    iterations = 100 if quick else 300

    def seconds(num, dim, batch, width, count):
        model = otf.models.squared_observation(dim=dim, noise=0.4, observation_scale=0.5, static=True)
        update = otf.ot(num_iterations=count, batch_size=batch, width=width, concavity_points=0)
        particles = jax.vmap(model.sample_initial)(jax.random.split(jax.random.key(1), num))

        def analysis(key, particles):
            state = update.init(key, particles, model)
            return update.apply(key, state, particles, jnp.ones(dim), model)[0]

        return timed(analysis, jax.random.key(2), particles, repeats=3)

    def rate(num, dim, batch, width, marginal=False):
        """Iterations per second of a whole update; with ``marginal``, also of the training loop
        alone: 2 x iterations minus 1 x iterations, which cancels the per-update O(N) work
        (simulating N observations, transporting the N particles once)."""
        result = seconds(num, dim, batch, width, iterations)
        row = {"iterations_per_s": iterations / result["seconds"], "compile_s": result["compile_s"]}
        if marginal:
            longer = seconds(num, dim, batch, width, 2 * iterations)
            row["marginal_iterations_per_s"] = iterations / (longer["seconds"] - result["seconds"])
            row["per_update_overhead_s"] = 2 * result["seconds"] - longer["seconds"]
        return row

    sweeps = {
        "batch (N=10^4, n=2, width 32)": [("batch", b, rate(10_000, 2, b, 32)) for b in (32, 64, 128, 256, 512, 1024)],
        "width (N=10^4, n=2, batch 128)": [("width", w, rate(10_000, 2, 128, w)) for w in (16, 32, 64, 128)],
        "n (N=10^4, batch 128, width 32)": [("n", d, rate(10_000, d, 128, 32)) for d in (1, 2, 5, 10, 20, 40)],
        "N (n=2, batch 128, width 32)": [("N", n, rate(n, 2, 128, 32, marginal=True))
                                         for n in (1_000, 10_000, 100_000, 1_000_000)],
    }
    for name, rows in sweeps.items():
        for axis, value, row in rows:
            marginal = (f"  training loop alone {row['marginal_iterations_per_s']:9.1f} it/s"
                        if "marginal_iterations_per_s" in row else "")
            print(f"OT {name:34s} {axis}={value:8d}: {row['iterations_per_s']:9.1f} it/s{marginal}  "
                  f"compile {row['compile_s']:.1f} s", flush=True)
    n_rows = sweeps["N (n=2, batch 128, width 32)"]
    fit = exponent([v for _, v, _ in n_rows], [1 / r["marginal_iterations_per_s"] for _, _, r in n_rows])
    return {"iterations": iterations, "sweeps": {k: [{"axis": a, "value": v, **r} for a, v, r in rows]
                                                 for k, rows in sweeps.items()},
            "seconds_per_iteration_exponent_in_N": fit}


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def write(out: str, results: dict) -> None:
    write_text_atomic(os.path.join(out, "scaling.json"), json.dumps(results, indent=2))
    lines = ["# Scaling (benchmarks/scaling.py)", "", f"device: {results['device']}", ""]
    if "particles" in results:
        part = results["particles"]
        lines += [f"## Lorenz-63: time and memory vs N ({part['cycles']}-cycle filter, 25 RK4 steps a cycle)", "",
                  "| update | N | analysis ms | cycle ms | filter memory MiB | process peak RSS MiB |",
                  "|--|--:|--:|--:|--:|--:|"]
        for name, rows in part["rows"].items():
            for r in rows:
                rss = r.get("process_peak_rss_bytes")
                lines.append(f"| {name} | {r['N']:,} | {r['analysis_s'] * 1e3:.3f} | {r['filter_s_per_cycle'] * 1e3:.3f} | "
                             f"{r['filter_memory_bytes'] / 2**20:.1f} | {'-' if rss is None else f'{rss / 2**20:.0f}'} |")
        lines += ["", "filter memory: XLA's allocation for the compiled 20-cycle filter (arguments, "
                  "outputs, temporaries); process peak RSS: a fresh Python process that imports "
                  "JAX, compiles and runs that filter (runtime and compiler included)."]
        lines += ["", "| update | exponent b (analysis, N >= 1e4) | (analysis, all N) | (cycle, N >= 1e4) | (memory, N >= 1e4) |",
                  "|--|--:|--:|--:|--:|"]
        for name, fit in part["fits"].items():
            lines.append("| " + name + " | " + " | ".join(_fmt(v) for v in fit.values()) + " |")
        lines.append("")
    if "dimension" in results:
        dim = results["dimension"]
        lines += ["## Lorenz-96: time vs n", "", "| update | n | analysis ms | cycle ms |", "|--|--:|--:|--:|"]
        for name, rows in dim["rows"].items():
            for r in rows:
                lines.append(f"| {name} | {r['n']} | {r['analysis_s'] * 1e3:.3f} | {r['filter_s_per_cycle'] * 1e3:.3f} |")
        lines += [""] + [f"- {name}: fitted exponent in n (n >= 100): analysis {_fmt(fit['analysis_exponent'])}, "
                         f"cycle {_fmt(fit['cycle_exponent'])}" for name, fit in dim["fits"].items()] + [""]
    if "ot" in results:
        ot = results["ot"]
        lines += [f"## OT update: outer iterations per second ({ot['iterations']} iterations timed)", "",
                  "| sweep | value | iterations / s (whole update) | training loop alone, it / s | "
                  "per-update O(N) work, s | compile s |", "|--|--:|--:|--:|--:|--:|"]
        for name, rows in ot["sweeps"].items():
            for r in rows:
                loop = r.get("marginal_iterations_per_s")
                overhead = r.get("per_update_overhead_s")
                lines.append(f"| {name} | {r['axis']} = {r['value']:,} | {r['iterations_per_s']:.1f} | "
                             f"{'-' if loop is None else f'{loop:.1f}'} | "
                             f"{'-' if overhead is None else f'{overhead:.4f}'} | {r['compile_s']:.1f} |")
        lines += ["", f"Training loop: seconds per iteration ~ N^{_fmt(ot['seconds_per_iteration_exponent_in_N'])} "
                  "at a fixed mini-batch of 128 (the per-update work on all N particles is separate).", ""]
    write_text_atomic(os.path.join(out, "scaling.md"), "\n".join(lines) + "\n")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default="particles,dimension,ot")
    parser.add_argument("--quick", action="store_true", help="N up to 10^4, n up to 100 (a smoke run)")
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--rss-child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.rss_child:
        name, num, cycles = args.rss_child
        run_filter_once(name, int(num), int(cycles))
        return
    results = {"device": str(jax.devices()[0]), "jax": jax.__version__}
    existing = os.path.join(args.out, "scaling.json")
    if os.path.exists(existing) and not args.quick:  # keep the parts not rerun
        with open(existing) as stream:
            results.update({k: v for k, v in json.load(stream).items() if k not in results})
    parts = args.parts.split(",")
    if "particles" in parts:
        counts = (100, 1_000, 10_000) if args.quick else (100, 1_000, 10_000, 100_000, 1_000_000)
        results["particles"] = particle_scaling(counts)
        write(args.out, results)
    if "dimension" in parts:
        dims = (40, 100) if args.quick else (40, 100, 200, 500, 1000)
        results["dimension"] = dimension_scaling(dims)
        write(args.out, results)
    if "ot" in parts:
        results["ot"] = ot_scaling(args.quick)
        write(args.out, results)


if __name__ == "__main__":
    main()
