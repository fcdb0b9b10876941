"""LETKF on Lorenz-96 from n = 40 to 40,000: time per assimilation cycle, memory, RMSE.

Run (from the repository root):

    PYTHONPATH=. python benchmarks/letkf_scaling.py                    # the full table
    PYTHONPATH=. python benchmarks/letkf_scaling.py --dims 40 400 --cycles 60   # a quick check

For each state dimension n, observed components (all, or every second one) and ensemble size N:

- truth: Lorenz-96 (F = 8, one RK4 step of 0.05 between observations, Sakov & Oke's setting),
  spun up for 1,000 steps from a perturbed rest state onto the attractor, then ``--cycles``
  observations with noise std 1 (variance 1, as DAPPER's sakov2008);
- filter: ``letkf(localisation(model.geometry, radius=4), inflation)`` started from
  truth + N(0, 1) noise (an ensemble of the attractor's size of error), ``save_every=0``;
- RMSE: the mean over the second half of the cycles of the per-cycle RMSE over the n
  components of the analysis mean; the observation noise std is 1, so an RMSE below 1 means
  the filter extracts more than the observations alone give;
- time per cycle: the filter's wall time after compilation (median of ``--repeats`` calls)
  divided by the number of cycles (propagation + analysis);
- memory: XLA's buffer sizes of the compiled filter (``compiled.memory_analysis()``:
  arguments + outputs + temporaries), deterministic, and the process's peak RSS.

The fitted exponent is the slope of log(time per cycle) against log(n) from n = 400 up (least
squares), per (observed, N). Results: ``benchmarks/results/letkf_scaling.{md,json,png}``.
"""

from __future__ import annotations

import argparse
import json
import os

# One BLAS thread: jaxlib's CPU LAPACK calls (Cholesky, eigh, triangular solves) go through
# OpenBLAS, whose threads fight XLA's own on a small machine (2 cores: the L96 perturbed EnKF
# took 133 instead of 84 us a cycle). Set before numpy, scipy and jax load; children inherit it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import platform
import resource
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter as otf

HERE = os.path.dirname(os.path.abspath(__file__))
RADIUS = 4.0
INFLATION = {20: 1.05, 40: 1.03}


def truth_and_observations(key, n, observed, cycles):
    model = otf.models.lorenz96(dim=n, observed=observed)
    spin_key, run_key = jax.random.split(key)
    rest = 8.0 + 0.01 * jax.random.normal(spin_key, (n,))
    spin = otf.models.lorenz96(dim=n, steps_per_observation=1000, observed=[0])
    start = spin.sample_transition(spin_key, rest)
    states, observations = jax.jit(_continue, static_argnums=3)(model, run_key, start, cycles)
    return model, start, states, observations


def _continue(model, key, start, cycles):
    def step(x, step_key):
        transition_key, observation_key = jax.random.split(step_key)
        x = model.sample_transition(transition_key, x)
        return x, (x, model.sample_observation(observation_key, x))

    _, (states, observations) = jax.lax.scan(step, start, jax.random.split(key, cycles))
    return states, observations


def measure(n, every, num_particles, cycles, repeats):
    observed = np.arange(0, n, every)
    model, start, states, observations = truth_and_observations(jax.random.key(n), n, observed, cycles)
    update = otf.letkf(otf.localisation(model.geometry, RADIUS), inflation=INFLATION[num_particles])
    initial = start + jax.random.normal(jax.random.key(1), (num_particles, n))

    @jax.jit
    def run(key, initial, observations, states):
        result = otf.run_filter(key, model, update, observations, num_particles, save_every=0,
                                initial_particles=initial)
        errors = jnp.sqrt(jnp.mean((result.mean - states) ** 2, axis=-1))
        return jnp.mean(errors[cycles // 2:]), jnp.mean(result.spread[cycles // 2:])

    start_compile = time.perf_counter()
    compiled = run.lower(jax.random.key(2), initial, observations, states).compile()
    compile_seconds = time.perf_counter() - start_compile
    memory = compiled.memory_analysis()
    buffers = None
    if memory is not None:
        buffers = int(memory.argument_size_in_bytes + memory.output_size_in_bytes
                      + memory.temp_size_in_bytes)
    times = []
    for _ in range(repeats):
        begin = time.perf_counter()
        rmse, spread = jax.block_until_ready(compiled(jax.random.key(2), initial, observations, states))
        times.append(time.perf_counter() - begin)
    return dict(
        n=n, observed_every=every, m=int(observed.size), N=num_particles, cycles=cycles,
        neighbours=int(update.apply.args[0].localisation.neighbours.shape[1]),
        rmse=float(rmse), spread=float(spread), seconds_per_cycle=float(np.median(times)) / cycles,
        compile_seconds=compile_seconds, xla_bytes=buffers,
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    )


def fitted_exponent(rows):
    large = [r for r in rows if r["n"] >= 400]
    if len(large) < 2:
        return None
    slope, _ = np.polyfit(np.log([r["n"] for r in large]), np.log([r["seconds_per_cycle"] for r in large]), 1)
    return float(slope)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dims", type=int, nargs="+", default=[40, 400, 4000, 40000])
    parser.add_argument("--every", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--particles", type=int, nargs="+", default=[20, 40])
    parser.add_argument("--cycles", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", default=os.path.join(HERE, "results", "letkf_scaling"))
    args = parser.parse_args()
    started = time.time()
    rows = []
    for every in args.every:
        for num_particles in args.particles:
            for n in args.dims:
                row = measure(n, every, num_particles, args.cycles, 1 if n >= 40000 else args.repeats)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    fits = {f"every {every}, N = {num}": fitted_exponent(
        [r for r in rows if r["observed_every"] == every and r["N"] == num])
        for every in args.every for num in args.particles}
    meta = dict(date=time.strftime("%Y-%m-%d %H:%M"), platform=platform.platform(), cpus=os.cpu_count(),
                jax=jax.__version__, backend=jax.default_backend(), device=str(jax.devices()[0]),
                radius=RADIUS, inflation=INFLATION, cycles=args.cycles,
                script_seconds=round(time.time() - started, 1))
    with open(args.output + ".json", "w") as handle:
        json.dump(dict(meta=meta, rows=rows, exponents=fits), handle, indent=1)
    write_markdown(args.output, meta, rows, fits)
    plot(args.output, rows)


def write_markdown(output, meta, rows, fits):
    lines = [
        "# LETKF on Lorenz-96: scaling in the state dimension n",
        "",
        f"{meta['date']}; {meta['platform']}; {meta['cpus']} CPUs; JAX {meta['jax']} on "
        f"{meta['device']}. Gaspari-Cohn radius {meta['radius']}, inflation {meta['inflation']} "
        f"(by N), {meta['cycles']} cycles (one RK4 step of 0.05 each), observation noise std 1; "
        f"RMSE and spread averaged over the second half. Script time {meta['script_seconds']} s.",
        "",
        "| observed | n | m | N | K | RMSE | spread | ms / cycle | us / cycle / coordinate "
        "| compile s | XLA buffers MB | peak RSS MB |",
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for r in rows:
        xla = f"{r['xla_bytes'] / 2**20:.1f}" if r["xla_bytes"] is not None else "–"
        lines.append(
            f"| {'all' if r['observed_every'] == 1 else 'every 2nd'} | {r['n']:,} | {r['m']:,} | "
            f"{r['N']} | {r['neighbours']} | {r['rmse']:.3f} | {r['spread']:.3f} | "
            f"{1e3 * r['seconds_per_cycle']:.2f} | {1e6 * r['seconds_per_cycle'] / r['n']:.2f} | "
            f"{r['compile_seconds']:.1f} | {xla} | {r['peak_rss_mb']:.0f} |")
    lines += ["", "Fitted exponent of the time per cycle in n (n >= 400; 1 = linear):", ""]
    lines += [f"- {name}: {value:.3f}" if value is not None else f"- {name}: –" for name, value in fits.items()]
    lines += ["", "K: the most observations within the taper's reach of one coordinate. Peak RSS is "
              "the process's so far (cumulative over the rows)."]
    with open(output + ".md", "w") as handle:
        handle.write("\n".join(lines) + "\n")
    print("\n".join(lines))


def plot(output, rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for every in sorted({r["observed_every"] for r in rows}):
        for num in sorted({r["N"] for r in rows}):
            chosen = [r for r in rows if r["observed_every"] == every and r["N"] == num]
            label = f"{'all' if every == 1 else 'every 2nd'} observed, N = {num}"
            dims = [r["n"] for r in chosen]
            left.loglog(dims, [1e3 * r["seconds_per_cycle"] for r in chosen], "o-", label=label)
            right.semilogx(dims, [r["rmse"] for r in chosen], "o-", label=label)
    dims = np.array(sorted({r["n"] for r in rows}), float)
    reference = [r for r in rows if r["n"] == dims[-1]]
    if reference:
        anchor = min(1e3 * r["seconds_per_cycle"] for r in reference)
        left.loglog(dims, anchor * dims / dims[-1], "k--", lw=1, label="linear in n")
    left.set(xlabel="state dimension n", ylabel="time per assimilation cycle (ms)",
             title="LETKF cost (2-core CPU)")
    right.axhline(1.0, color="k", ls=":", lw=1, label="observation noise std")
    right.set(xlabel="state dimension n", ylabel="analysis RMSE", ylim=(0, 1.2),
              title="LETKF accuracy")
    left.legend(fontsize=8)
    right.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(output + ".png", dpi=120)


if __name__ == "__main__":
    main()
