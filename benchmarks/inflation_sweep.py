"""An inflation sweep as ONE compiled program (traced inflation) vs one program per value.

Run (from the repository root):

    PYTHONPATH=. python benchmarks/inflation_sweep.py            # L63 + L96 PertObs, 500 cycles
    PYTHONPATH=. python benchmarks/inflation_sweep.py --all --cycles 1001   # + L96 Sqrt, 1001
    PYTHONPATH=. python benchmarks/inflation_sweep.py --cycles 200 --seeds 2   # a faster check

The default run took 7 minutes on 2 cores shared with other jobs (load average 8-9) and used 5
CPU-minutes, i.e. about 3 minutes on 2 idle cores; most of it is XLA compilation (7 programs per
configuration). ``--all --cycles 1001`` took 9 minutes (load average 5-6).

Configurations (``ot_filter/experiments/twin_configurations.py``; DAPPER's tuned inflation in
brackets, only the inflation is swept):

    L63/EnKF-Sqrt-N10     lorenz63()  enkf(perturbed=False, rotate=True), N=10   [1.02]
    L96/EnKF-PertObs-N40  lorenz96()  enkf(perturbed=True), N=40                 [1.06]
    L96/EnKF-Sqrt-N24     lorenz96()  enkf(perturbed=False, rotate=True), N=24   [1.013]  (--all)

Each is filtered for every inflation of a grid (``--grid START STOP COUNT``, default 1.00 ..
1.10, 6 values) and every one of ``--seeds`` twin truths (default 4; truths and observations
drawn once with ``ot_filter.simulate`` from ``key(0)``, filter keys split from ``key(1)``;
truth simulation is outside every timing). One run filters ``--cycles`` observations (default
500, about half of DAPPER's 1001, to keep the default run short) and returns rmse.a: the
per-analysis RMSE over components of the filter mean, averaged over the analyses after DAPPER's
burn-in (``TWIN_EXPERIMENTS``: L63 k >= 64 of 1001, L96 k >= 400 of 1001), scaled to the cycles:
k >= round(burn_in * cycles / 1001), i.e. k >= 32 (L63) and k >= 200 (L96) of 500.
``save_every=0``. float32 (JAX's default).

Two ways to run the sweep:

(a) one program: ``jax.jit(jax.vmap(jax.vmap(one_run, (None, 0)), (0, None)))`` over
    inflation x seed, the inflation a traced argument (``enkf(inflation=a)`` with ``a`` traced;
    the update is a pytree whose leaf is that number). Compile seconds: ``.lower(...).compile()``
    (tracing, lowering, XLA compilation); run seconds: median of ``--repeats`` (3) calls of the
    compiled program, ``block_until_ready``.
(b) one program per value, as without traced settings: for each inflation, ``jax.clear_caches()``,
    the update built from the Python float and closed over by a fresh function, ``jax.jit(
    jax.vmap(run over seeds))``, compiled (``.lower(...).compile()``) and run (median of
    ``--repeats``). Reported: compile and run seconds summed over the values, and the number of
    traces and XLA backend compilations seen (``jax.monitoring`` events), one per value.

Run seconds are also given as the minimum of the calls: on a CPU shared with other jobs single
calls of the batched programs were seen to take up to 50 times their usual time.

Also reported: the speed-ups (b) / (a) for compile, run and compile + one run (what a user
waits for a sweep); rmse.a per value (mean over seeds, standard error) of (a) and (b) and the
largest |(a) - (b)| per value (float32 against float32: (a) multiplies by a traced inflation in
a batched program, (b) by a constant folded into its own program, so the roundings differ and
the chaotic model amplifies them: the per-analysis RMSE of (a) and (b) is compared over the first
10 analyses, and the analysis where the two first differ by more than 1e-3 is reported); and a
no-recompilation check: the jitted sweep of (a) is called with the grid and then with a NEW grid
(the old one shifted by half a step); the number of traces of ``one_run`` (a Python counter) and
of XLA backend compilations during that second call must be zero, and its seconds are those of
a run (the first call, with the grid, also shows whether the jitted function reuses the program
that ``.lower(...).compile()`` built).

Output: a table on stdout, ``benchmarks/results/inflation_sweep.json`` / ``.md`` and the figure
``benchmarks/results/inflation_sweep.png`` (rmse.a vs inflation per configuration, mean over
seeds +- 1 standard error).
"""

from __future__ import annotations

import argparse
import collections
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
from ot_filter.experiments.twin_configurations import TWIN_CONFIGURATIONS, TWIN_EXPERIMENTS

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_CONFIGS = ("L63/EnKF-Sqrt-N10", "L96/EnKF-PertObs-N40")
ALL_CONFIGS = (*DEFAULT_CONFIGS, "L96/EnKF-Sqrt-N24")
TRUTH_SEED = 0
FILTER_SEED = 1
EARLY = 10  # analyses over which (a) and (b) must agree to rounding
PART_THRESHOLD = 1e-3  # per-analysis RMSE difference at which (a) and (b) count as parted

TRACES: collections.Counter = collections.Counter()  # traces of one_run, per configuration
BACKEND_COMPILES = [0]  # XLA backend compilations seen (jax.monitoring)


def _on_event_duration(event: str, duration: float, **kwargs) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        BACKEND_COMPILES[0] += 1


jax.monitoring.register_event_duration_secs_listener(_on_event_duration)


def burn_in(config, cycles: int) -> int:
    experiment = config.experiment
    return int(round(experiment.burn_in * cycles / experiment.num_analyses))


def simulate_truths(model_name: str, num_seeds: int, cycles: int):
    """``(keys[S], observations[S, T, m], states[S, T, n])`` of S twin truths (filter keys)."""
    model = TWIN_EXPERIMENTS[model_name].make_model()
    keys = jax.random.split(jax.random.key(TRUTH_SEED), num_seeds)
    states, observations = jax.jit(
        jax.vmap(lambda key: ot_filter.simulate(key, model, cycles)))(keys)
    filter_keys = jax.random.split(jax.random.key(FILTER_SEED), num_seeds)
    return jax.block_until_ready((filter_keys, observations, states))


def make_rmse_a(config, cycles: int):
    """``rmse_a(update, (key, observations[T, m], states[T, n])) -> (rmse.a, rmse[T])``: rmse.a
    and the RMSE of the filter mean at each analysis (to see where (a) and (b) part)."""
    model = config.experiment.make_model()
    first = burn_in(config, cycles)

    def rmse_a(update, seed):
        key, observations, states = seed
        result = ot_filter.run_filter(key, model, update, observations, config.num_particles,
                                      save_every=0)
        rmse = ot_filter.metrics.rmse(result.mean, states)
        return jnp.mean(rmse[first:]), rmse

    return rmse_a


def timed(function, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(function(*args))
    return out, time.perf_counter() - start


def measure(config, data, grid: np.ndarray, new_grid: np.ndarray, cycles: int,
            repeats: int) -> dict:
    rmse_a = make_rmse_a(config, cycles)
    dtype = jnp.zeros(()).dtype
    inflations = jnp.asarray(grid, dtype)
    new_inflations = jnp.asarray(new_grid, dtype)

    # (a) one program over inflation x seed, the inflation traced.
    def one_run(inflation, seed):
        TRACES[config.name, "a"] += 1
        return rmse_a(config.build_update(inflation=inflation), seed)

    sweep = jax.jit(jax.vmap(jax.vmap(one_run, (None, 0)), (0, None)))
    start = time.perf_counter()
    compiled = sweep.lower(inflations, data).compile()
    a_compile = time.perf_counter() - start
    a_runs = []
    for _ in range(repeats):
        (a_rmse, a_path), seconds = timed(compiled, inflations, data)
        a_runs.append(seconds)
    a_rmse, a_path = np.asarray(a_rmse, float), np.asarray(a_path, float)
    a_traces = TRACES[config.name, "a"]

    # No recompilation: the jitted sweep with the grid, then with a NEW grid (arrays made first).
    traces, compiles = TRACES[config.name, "a"], BACKEND_COMPILES[0]
    _, first_seconds = timed(sweep, inflations, data)
    first_call = {"seconds": first_seconds, "traces": TRACES[config.name, "a"] - traces,
                  "backend_compiles": BACKEND_COMPILES[0] - compiles}
    traces, compiles = TRACES[config.name, "a"], BACKEND_COMPILES[0]
    (new_rmse, _), new_seconds = timed(sweep, new_inflations, data)
    recompile_check = {
        "new_grid": [float(v) for v in new_grid],
        "seconds": new_seconds,
        "traces": TRACES[config.name, "a"] - traces,
        "backend_compiles": BACKEND_COMPILES[0] - compiles,
        "jit_cache_size": sweep._cache_size(),
        "rmse_a": np.asarray(new_rmse, float).tolist(),
        "first_jit_call_same_grid": first_call,  # after the AOT compile: reuses it or not
    }

    # (b) one program per value: the inflation a Python float closed over, a fresh function.
    b_compile, b_run, b_run_min, b_rmse, b_path, b_traces, b_compiles = [], [], [], [], [], 0, 0
    for value in grid:
        jax.clear_caches()
        update = config.build_update(inflation=float(value))  # static: a Python float

        def runs(seeds, update=update):
            TRACES[config.name, "b"] += 1
            return jax.vmap(lambda seed: rmse_a(update, seed))(seeds)

        traces, compiles = TRACES[config.name, "b"], BACKEND_COMPILES[0]
        start = time.perf_counter()
        program = jax.jit(runs).lower(data).compile()
        b_compile.append(time.perf_counter() - start)
        b_traces += TRACES[config.name, "b"] - traces
        b_compiles += BACKEND_COMPILES[0] - compiles
        seconds = []
        for _ in range(repeats):
            (rmse_value, path), run_seconds = timed(program, data)
            seconds.append(run_seconds)
        b_run.append(statistics.median(seconds))
        b_run_min.append(min(seconds))
        b_rmse.append(np.asarray(rmse_value, float))
        b_path.append(np.asarray(path, float))
    b_rmse, b_path = np.stack(b_rmse), np.stack(b_path)

    num_seeds = a_rmse.shape[1]
    difference = np.abs(a_rmse - b_rmse)
    # Where the two runs part: per-analysis RMSE difference over the first EARLY analyses, and
    # the first analysis at which it exceeds PART_THRESHOLD (cycles if never), per cell.
    path_difference = np.abs(a_path - b_path)  # [values, seeds, T]
    parted = path_difference > PART_THRESHOLD
    first_parted = np.where(parted.any(axis=-1), parted.argmax(axis=-1), cycles)
    a = {"compile_seconds": a_compile, "run_seconds": statistics.median(a_runs),
         "run_seconds_min": min(a_runs), "run_seconds_all": a_runs, "traces": a_traces}
    b = {"compile_seconds": sum(b_compile), "run_seconds": sum(b_run),
         "run_seconds_min": sum(b_run_min),
         "compile_seconds_per_value": b_compile, "run_seconds_per_value": b_run,
         "run_seconds_min_per_value": b_run_min, "traces": b_traces, "backend_compiles": b_compiles}
    entry = {
        "name": config.name,
        "label": config.label,
        "num_particles": config.num_particles,
        "tuned_inflation": config.settings["inflation"],
        "published_rmse": config.expected_rmse,
        "dtype": str(dtype),
        "cycles": cycles,
        "first_averaged": burn_in(config, cycles),
        "grid": [float(v) for v in grid],
        "a": a,
        "b": b,
        "speedup_compile": b["compile_seconds"] / a["compile_seconds"],
        "speedup_run": b["run_seconds"] / a["run_seconds"],
        "speedup_run_min": b["run_seconds_min"] / a["run_seconds_min"],
        "speedup_total": (b["compile_seconds"] + b["run_seconds"])
        / (a["compile_seconds"] + a["run_seconds"]),
        "rmse_a": {
            "a": a_rmse.tolist(),
            "b": b_rmse.tolist(),
            "a_mean": a_rmse.mean(axis=1).tolist(),
            "a_stderr": (a_rmse.std(axis=1, ddof=1) / np.sqrt(num_seeds)).tolist()
            if num_seeds > 1 else [0.0] * len(grid),
            "b_mean": b_rmse.mean(axis=1).tolist(),
            "max_abs_difference_per_value": difference.max(axis=1).tolist(),
            "max_abs_difference": float(difference.max()),
            "max_relative_difference": float((difference / np.abs(b_rmse)).max()),
            f"max_abs_difference_first_{EARLY}_analyses": float(path_difference[..., :EARLY].max()),
            "first_analysis_differing_by_more_than": PART_THRESHOLD,
            "first_analysis_differing": first_parted.tolist(),
        },
        "recompile_check": recompile_check,
    }
    print(f"{config.name}: (a) compile {a_compile:.2f} s run {a['run_seconds']:.3f} s; "
          f"(b) compile {b['compile_seconds']:.2f} s run {b['run_seconds']:.3f} s "
          f"({b_compiles} compiles); max |a - b| {entry['rmse_a']['max_abs_difference']:.2e} "
          f"(first {EARLY} analyses {path_difference[..., :EARLY].max():.1e}); "
          f"new grid: {recompile_check['traces']} traces, "
          f"{recompile_check['backend_compiles']} compiles, {new_seconds:.3f} s",
          file=sys.stderr, flush=True)
    return entry


def markdown_report(report: dict) -> str:
    meta = report["meta"]
    lines = [
        "# Inflation sweep: one compiled program (traced inflation) vs one program per value",
        "",
        f"{meta['date']}; {meta['platform']}; {meta['cpu_count']} CPUs; JAX {meta['jax']} on "
        f"{meta['jax_device']}; {meta['dtype']}. {meta['seeds']} truths per configuration, "
        f"{meta['cycles']} cycles (analyses) per run, run seconds = median of "
        f"{meta['repeats']} calls. Total script time {meta['total_seconds']:.0f} s.",
        "",
        "(a): `jax.jit(jax.vmap(jax.vmap(one_run, (None, 0)), (0, None)))` over inflation x seed, "
        "one compilation. (b): for each value, `jax.clear_caches()` and a fresh `jax.jit` of the "
        "seed-vmapped run with the inflation a Python float closed over; seconds summed over "
        "values. "
        "Speed-up = (b) / (a); 'total' = compile + one run (medians). Run seconds: median of "
        "the calls, their minimum in brackets (on a CPU shared with other jobs the minimum is "
        "the steadier figure).",
        "",
        "| configuration | values x seeds | (a) compile s | (a) run s (min) | (b) compile s "
        "| (b) run s (min) | (b) compiles | speed-up compile | speed-up run (min) | speed-up total "
        f"| max abs(a - b) rmse.a | max abs(a - b) RMSE, first {EARLY} analyses "
        "| analyses before they part (min / median) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in report["rows"]:
        a, b = row["a"], row["b"]
        lines.append(
            f"| {row['name']} | {len(row['grid'])} x {meta['seeds']} | {a['compile_seconds']:.2f} "
            f"| {a['run_seconds']:.3f} ({a['run_seconds_min']:.3f}) | {b['compile_seconds']:.2f} "
            f"| {b['run_seconds']:.3f} ({b['run_seconds_min']:.3f}) | {b['backend_compiles']} "
            f"| {row['speedup_compile']:.1f}x | {row['speedup_run']:.2f}x "
            f"({row['speedup_run_min']:.2f}x) "
            f"| {row['speedup_total']:.1f}x | {row['rmse_a']['max_abs_difference']:.1e} "
            f"| {row['rmse_a'][f'max_abs_difference_first_{EARLY}_analyses']:.1e} "
            f"| {np.min(row['rmse_a']['first_analysis_differing'])} / "
            f"{np.median(row['rmse_a']['first_analysis_differing']):.0f} |")
    lines += ["", "No recompilation: the jitted sweep (a) called with a new grid (the grid shifted "
              "by half a step) after a call with the grid:", "",
              "| configuration | new grid | traces of one_run | XLA compilations | seconds "
              "| (a) run s | jit cache entries "
              "| first jit call (same grid): traces / compilations |",
              "|---|---|---:|---:|---:|---:|---:|---|"]
    for row in report["rows"]:
        check = row["recompile_check"]
        lines.append(
            f"| {row['name']} | {', '.join(f'{v:.3f}' for v in check['new_grid'])} "
            f"| {check['traces']} | {check['backend_compiles']} | {check['seconds']:.3f} "
            f"| {row['a']['run_seconds']:.3f} | {check['jit_cache_size']} "
            f"| {check['first_jit_call_same_grid']['traces']} / "
            f"{check['first_jit_call_same_grid']['backend_compiles']} |")
    for row in report["rows"]:
        r = row["rmse_a"]
        lines += ["", f"## {row['name']} ({row['label'].split(' infl')[0]}, N = "
                  f"{row['num_particles']}; DAPPER's inflation {row['tuned_inflation']}, "
                  f"published rmse.a {row['published_rmse']})", "",
                  "| inflation | (a) rmse.a mean +- s.e. | (b) rmse.a mean "
                  "| max abs(a - b) over seeds "
                  "| (a) per seed |", "|---:|---:|---:|---:|---|"]
        for i, value in enumerate(row["grid"]):
            per_seed = " ".join(f"{v:.3f}" for v in r["a"][i])
            lines.append(f"| {value:.3f} | {r['a_mean'][i]:.4f} +- {r['a_stderr'][i]:.4f} "
                         f"| {r['b_mean'][i]:.4f} | {r['max_abs_difference_per_value'][i]:.1e} "
                         f"| {per_seed} |")
        check = row["recompile_check"]
        new = " ".join(f"{v:.3f}: {np.mean(s):.4f}"
                       for v, s in zip(check["new_grid"], check["rmse_a"]))
        lines.append(f"\nNew grid (second call, no recompilation), mean rmse.a: {new}")
    lines += ["", "rmse.a: mean over the analyses k >= first averaged (DAPPER's burn-in, scaled "
              "to the cycles) of the RMSE over components of the filter mean. (a) and (b) use "
              "the same truths, observations and filter keys, both float32; their difference is "
              "rounding (a traced multiplier in a batched program vs a constant folded into its "
              "own): rounding-level over the first analyses, then amplified by the chaotic model "
              f"until the two runs part ('before they part': the first analysis whose RMSE differs "
              f"by more than {PART_THRESHOLD:g}; {meta['cycles']} if never), after which they are "
              "two filters with the same statistics, so rmse.a differs at the level of its "
              "seed-to-seed noise, not more.", ""]
    return "\n".join(lines)


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    rows = report["rows"]
    fig, axes = plt.subplots(1, len(rows), figsize=(max(4.8 * len(rows), 9), 4.8), squeeze=False)
    seeds = report["meta"]["seeds"]
    for ax, row in zip(axes[0], rows):
        r = row["rmse_a"]
        grid = np.asarray(row["grid"])
        mean, stderr = np.asarray(r["a_mean"]), np.asarray(r["a_stderr"])
        ax.plot(grid, mean, "o-", color="C0", label="(a) one program, traced inflation")
        ax.fill_between(grid, mean - stderr, mean + stderr, color="C0", alpha=0.25,
                        label="(a) +- 1 standard error")
        ax.plot(grid, r["b_mean"], "x", color="C3", markersize=9, mew=1.8,
                label="(b) one program per value")
        check = row["recompile_check"]
        new = np.asarray(check["rmse_a"])
        new_stderr = new.std(axis=1, ddof=1) / np.sqrt(seeds) if seeds > 1 else 0 * new[:, 0]
        ax.errorbar(check["new_grid"], new.mean(axis=1), yerr=new_stderr, fmt="s", color="C2",
                    mfc="none", capsize=3, label="(a) new grid, no recompilation")
        ax.axvline(row["tuned_inflation"], color="grey", ls="--", lw=1,
                   label="DAPPER's tuned inflation")
        if row["published_rmse"] is not None:
            ax.axhline(row["published_rmse"], color="grey", ls=":", lw=1,
                       label="rmse.a published by DAPPER (1001 cycles)")
        values = np.concatenate([mean - stderr, mean + stderr, r["b_mean"]])
        if np.max(values) > 4 * np.min(values[values > 0]):  # a diverging value: log scale
            ax.set_yscale("log")
            ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 3.0, 5.0)))
            ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
            ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("multiplicative inflation")
        ax.set_ylabel(f"rmse.a (mean over {seeds} truths)")
        ax.set_title(f"{row['name']}\n({row['cycles']} cycles, rmse.a over k >= "
                     f"{row['first_averaged']})", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle(f"Inflation sweep: rmse.a vs inflation, mean over {seeds} truths +- 1 standard "
                 f"error ({report['meta']['dtype']}, {report['meta']['jax_device']})", fontsize=11)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", default=list(DEFAULT_CONFIGS),
                        choices=sorted(c for c in TWIN_CONFIGURATIONS if "EnKF" in c),
                        help=f"default {' '.join(DEFAULT_CONFIGS)}")
    parser.add_argument("--all", action="store_true", help=f"all of {' '.join(ALL_CONFIGS)}")
    parser.add_argument("--grid", nargs=3, type=float, default=[1.0, 1.1, 6],
                        metavar=("START", "STOP", "COUNT"), help="inflation grid (linspace)")
    parser.add_argument("--seeds", type=int, default=4, help="twin truths (default 4)")
    parser.add_argument("--cycles", type=int, default=500,
                        help="analyses per run (default 500; DAPPER's 1001; burn-in scaled)")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls, median (default 3)")
    parser.add_argument("--output-dir", type=Path, default=RESULTS)
    args = parser.parse_args()

    start = time.perf_counter()
    count = int(args.grid[2])
    grid = np.linspace(args.grid[0], args.grid[1], count)
    step = (grid[1] - grid[0]) if count > 1 else 0.01
    new_grid = grid + step / 2
    configs = [TWIN_CONFIGURATIONS[name] for name in (ALL_CONFIGS if args.all else args.configs)]
    truths = {}
    for config in configs:  # simulated once per model, outside every timing
        if config.model_name not in truths:
            truths[config.model_name] = simulate_truths(config.model_name, args.seeds, args.cycles)
    rows = [measure(config, truths[config.model_name], grid, new_grid, args.cycles, args.repeats)
            for config in configs]

    meta = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "platform": platform.platform(terse=True),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jax_device": str(jax.devices()[0].device_kind),
        "ot_filter": ot_filter.__version__,
        "dtype": str(jnp.zeros(()).dtype),
        "seeds": args.seeds,
        "cycles": args.cycles,
        "repeats": args.repeats,
        "truth_seed": TRUTH_SEED,
        "filter_seed": FILTER_SEED,
        "total_seconds": time.perf_counter() - start,
    }
    report = {"meta": meta, "rows": rows}
    args.output_dir.mkdir(parents=True, exist_ok=True)
    markdown = markdown_report(report)
    (args.output_dir / "inflation_sweep.json").write_text(json.dumps(report, indent=1) + "\n")
    (args.output_dir / "inflation_sweep.md").write_text(markdown)
    plot(report, args.output_dir / "inflation_sweep.png")
    print(markdown)


if __name__ == "__main__":
    main()
