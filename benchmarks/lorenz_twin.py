"""Lorenz-63 / Lorenz-96 twin experiments: ot_filter against DAPPER 1.7.1, speed and rmse.a.

Run (from the repository root):

    PYTHONPATH=. python benchmarks/lorenz_twin.py --dapper-python /work/dapper-venv/bin/python
    PYTHONPATH=. python benchmarks/lorenz_twin.py --quick      # 2 seeds, 2 repeats: a fast check

Configurations (DAPPER's model files and their suggested tunings; last column the rmse.a they
publish; all defined in ``ot_filter/experiments/twin_configurations.py``):

    L63/EnKF-Sqrt-N10     lorenz63()  enkf(1.02, perturbed=False, rotate=True), N=10     0.60
    L63/PartFilt-N800     lorenz63()  sir('systematic', ess_threshold=0.2, jitter=0.9),
                                      N=800                                               0.28
    L96/EnKF-PertObs-N40  lorenz96()  enkf(1.06), N=40                                    0.22
    L96/EnKF-Sqrt-N24     lorenz96()  enkf(1.013, perturbed=False, rotate=True), N=24     0.18

``lorenz63()`` defaults to DAPPER's Lorenz63.sakov2012 (25 RK4 steps of 0.01 between
observations, all components observed with variance 2), ``lorenz96()`` to Lorenz96.sakov2008
(40 variables, one RK4 step of 0.05, all observed with variance 1). Both run 1001 analyses, as
DAPPER (Ko = 1000): 25,025 RK4 steps for L63, 1,001 for L96.

What is measured:

- rmse.a, as DAPPER defines it: at each analysis time the RMSE over components of the filter
  mean (``ot_filter.metrics.rmse(result.mean, states)``), averaged over the analysis times
  t > BurnIn. Analysis k (0-based) is at time dt_obs (k + 1); L63: BurnIn 16, dt_obs 0.25, so
  k >= 64 and 937 analyses are averaged; L96: BurnIn 20, dt_obs 0.05, k >= 400, 601 analyses.
- over ``--seeds`` independent truths (twin experiments: truth and observations drawn from the
  model with ``ot_filter.simulate``), all seeds in ONE compiled program (``jax.vmap`` over filter
  keys, observation sequences and truths); reported as mean, median and per-seed values.
- precision: the same truths/observations (simulated in float32 by this process) are filtered
  in float32 (JAX's default) here and in float64 by a child process of this script
  (``JAX_ENABLE_X64=1``), so the float32/float64 comparison is paired seed by seed.
- fast RNG: a second child times the same float32 code with ``JAX_THREEFRY_PARTITIONABLE=0``
  (JAX's older Threefry layout: different random streams, same distributions). On CPU its
  random bits cost several times less, which matters for the perturbed-observation EnKF; keep
  the default when sharding the particles over devices.
- vmapped: seconds per seed of the program that runs all ``--seeds`` twins at once (median of
  up to 3 calls), i.e. throughput when a user filters several truths or a sweep at once.
- compile time: ``jax.jit(twin).lower(...).compile()`` of one single-seed twin experiment
  (filter + rmse.a), i.e. tracing, lowering and XLA compilation.
- seconds: wall time of one whole single-seed twin experiment after compilation (the filter over
  1001 observations and its rmse.a, ``block_until_ready``), median of ``--repeats`` calls;
  ``save_every=0`` (no particle storage). Truth simulation is excluded, as in DAPPER.
- DAPPER (``--dapper-python``): ``benchmarks/dapper_baseline.py`` runs in a subprocess in the same
  invocation, over ``--dapper-seeds`` truths of its own: seconds of ``xp.assimilate`` only, with
  DAPPER's lightest statistics mode (``error_only``), median over seeds; rmse.a per seed. The
  speed-up is DAPPER's median seconds over ot_filter's median seconds (same machine, run one
  after the other, never concurrently).

Output: a Markdown table on stdout, and ``benchmarks/results/lorenz_twin.json`` / ``.md``.
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
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter
from ot_filter.experiments.twin_configurations import TWIN_CONFIGURATIONS, TWIN_EXPERIMENTS

BENCHMARKS = Path(__file__).resolve().parent
RESULTS = BENCHMARKS / "results"
TRUTH_SEED = 0
FILTER_SEED = 1


# A twin experiment: model, observation count (num_analyses) and DAPPER's averaging window
# (burn_in: index of the first averaged analysis; analyses_averaged: DAPPER's count, checked).
EXPERIMENTS = {"L63": TWIN_EXPERIMENTS["lorenz63"], "L96": TWIN_EXPERIMENTS["lorenz96"]}
EXPERIMENT_KEYS = {experiment.model_name: key for key, experiment in EXPERIMENTS.items()}


class Config(NamedTuple):
    name: str  # same key as in dapper_baseline.py
    experiment: str
    method: str  # DAPPER's name of the method
    num_particles: int
    make_update: Callable[[], ot_filter.BayesUpdate]
    published_rmse: float | None  # rmse.a in DAPPER's model file


CONFIGS = tuple(
    Config(c.name, EXPERIMENT_KEYS[c.model_name], c.label, c.num_particles, c.build_update,
           c.expected_rmse)
    for c in TWIN_CONFIGURATIONS.values()
)


# --------------------------------------------------------------------------------------------
# ot_filter measurements (run in float32 here and in float64 in a child process)
# --------------------------------------------------------------------------------------------


def simulate_truths(num_seeds: int) -> dict[str, dict[str, np.ndarray]]:
    """Per experiment, ``states[S, T, n]`` and ``observations[S, T, m]`` of S twin truths."""
    truths = {}
    for name, experiment in EXPERIMENTS.items():
        model = experiment.make_model()
        keys = jax.random.split(jax.random.key(TRUTH_SEED), num_seeds)
        states, observations = jax.jit(
            jax.vmap(lambda key: ot_filter.simulate(key, model, experiment.num_analyses))
        )(keys)
        truths[name] = {"states": np.asarray(states), "observations": np.asarray(observations)}
    return truths


def make_twin(config: Config) -> Callable:
    """``twin(key, observations[T, m], states[T, n]) -> (rmse_a, resample_fraction)``."""
    experiment = EXPERIMENTS[config.experiment]
    model = experiment.make_model()
    update = config.make_update()
    first = experiment.burn_in

    def twin(key, observations, states):
        result = ot_filter.run_filter(
            key, model, update, observations, config.num_particles, save_every=0
        )
        rmse_a = jnp.mean(ot_filter.metrics.rmse(result.mean, states)[first:])
        resampled = getattr(result.info, "resampled", None)  # SIR only
        fraction = jnp.nan if resampled is None else jnp.mean(resampled.astype(rmse_a.dtype))
        return rmse_a, fraction

    return twin


def measure_ot_filter(truths, repeats: int) -> dict:
    """rmse.a over all seeds (one vmapped program) and timing of one single-seed experiment."""
    dtype = jnp.zeros(()).dtype  # float32, or float64 under JAX_ENABLE_X64
    results = {}
    for config in CONFIGS:
        truth = truths[config.experiment]
        observations = jnp.asarray(truth["observations"], dtype)
        states = jnp.asarray(truth["states"], dtype)
        num_seeds = observations.shape[0]
        keys = jax.random.split(jax.random.key(FILTER_SEED), num_seeds)
        twin = make_twin(config)

        start = time.perf_counter()
        single = jax.jit(twin).lower(keys[0], observations[0], states[0]).compile()
        compile_seconds = time.perf_counter() - start
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            jax.block_until_ready(single(keys[0], observations[0], states[0]))
            seconds.append(time.perf_counter() - start)

        # One program for all seeds (vmapped; the EnKF avoids batched LAPACK triangular solves
        # and QR, which deadlocked jaxlib 0.10.2's CPU thread pool for 128+ simulations).
        start = time.perf_counter()
        batched = jax.jit(jax.vmap(twin)).lower(keys, observations, states).compile()
        batch_compile_seconds = time.perf_counter() - start
        batch_seconds = []
        for _ in range(min(repeats, 3)):
            start = time.perf_counter()
            rmse_a, resample_fraction = jax.block_until_ready(batched(keys, observations, states))
            batch_seconds.append(time.perf_counter() - start)

        rmse_a = np.asarray(rmse_a, float)
        entry = {
            "dtype": str(dtype),
            "compile_seconds": compile_seconds,
            "seconds": statistics.median(seconds),
            "seconds_all": seconds,
            "batch_seconds": statistics.median(batch_seconds),
            "batch_seconds_all": batch_seconds,
            "batch_seconds_per_seed": statistics.median(batch_seconds) / num_seeds,
            "threefry_partitionable": bool(jax.config.jax_threefry_partitionable),
            "batch_compile_seconds": batch_compile_seconds,
            "rmse_a": rmse_a.tolist(),
            "rmse_a_mean": float(np.mean(rmse_a)),
            "rmse_a_median": float(np.median(rmse_a)),
        }
        if not np.all(np.isnan(resample_fraction)):
            entry["resample_fraction"] = np.asarray(resample_fraction, float).tolist()
        results[config.name] = entry
        print(f"ot_filter {dtype} {config.name}: compile {compile_seconds:.2f} s, "
              f"run {entry['seconds']:.3f} s, rmse.a mean {entry['rmse_a_mean']:.4f}",
              file=sys.stderr, flush=True)
    return results


# --------------------------------------------------------------------------------------------
# Subprocesses: float64 child, DAPPER baseline
# --------------------------------------------------------------------------------------------


def run_child(truth_file: Path, repeats: int, **config: str) -> dict:
    """Re-runs this script's ot_filter measurements on the same truths with JAX configured by
    environment variables (e.g. JAX_ENABLE_X64="1"); returns its JSON."""
    env = dict(os.environ, **config)
    command = [sys.executable, str(Path(__file__).resolve()), "--child", str(truth_file),
               "--repeats", str(repeats)]
    completed = subprocess.run(command, env=env, stdout=subprocess.PIPE, text=True, check=True)
    return json.loads(completed.stdout)


def run_cuthbert(python: str, truths: dict, num_seeds: int, repeats: int) -> dict:
    """cuthbert on the same L63 truths (benchmarks/cuthbert_baseline.py in its own interpreter):
    {config name: {"seconds": [per seed], "compile_s", "rmse_a": [per seed]}, "_meta": ...}."""
    with tempfile.TemporaryDirectory() as directory:
        data = Path(directory) / "l63.npz"
        np.savez(data, states=truths["L63"]["states"][:num_seeds],
                 observations=truths["L63"]["observations"][:num_seeds])
        command = [python, str(BENCHMARKS / "cuthbert_baseline.py"), "--data", str(data),
                   "--repeats", str(repeats), "--api", "online"]
        completed = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=True)
    return json.loads(completed.stdout)


def run_dapper(python: str, num_seeds: int) -> dict:
    command = [python, str(BENCHMARKS / "dapper_baseline.py"), "--seeds", str(num_seeds)]
    completed = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=True)
    return json.loads(completed.stdout)


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def _fmt(value, digits=3):
    return "–" if value is None else f"{value:.{digits}f}"


def markdown_report(report: dict) -> str:
    meta = report["meta"]
    lines = [
        "# Lorenz twin experiments: ot_filter vs DAPPER",
        "",
        f"{meta['date']}; {meta['platform']}; {meta['cpu_count']} CPUs; JAX {meta['jax']} on "
        f"{meta['jax_device']}; DAPPER {meta.get('dapper', '–')} "
        f"({meta.get('dapper_stats', 'not run')}). ot_filter: {meta['seeds']} seeds, "
        f"median of {meta['repeats']} runs; DAPPER: {meta.get('dapper_seeds', 0)} seeds, "
        f"median seconds over seeds. Total script time {meta['total_seconds']:.0f} s.",
        "",
        "| experiment | method | N | ot_filter s | compile s | DAPPER s | speed-up | "
        "ot_filter rmse.a f32 mean / median | f64 rmse.a mean / median | "
        "DAPPER rmse.a mean / median | published rmse.a |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in report["rows"]:
        f32, f64, dapper = row["float32"], row.get("float64"), row.get("dapper")
        speedup = "–" if row["speedup"] is None else f"{row['speedup']:.1f}x"
        lines.append(
            f"| {row['experiment']} | {row['method']} | {row['num_particles']} "
            f"| {_fmt(f32['seconds'])} | {_fmt(f32['compile_seconds'], 2)} "
            f"| {_fmt(dapper and dapper['seconds'])} | "
            f"{speedup} "
            f"| {_fmt(f32['rmse_a_mean'])} / {_fmt(f32['rmse_a_median'])} "
            f"| {_fmt(f64 and f64['rmse_a_mean'])} / {_fmt(f64 and f64['rmse_a_median'])} "
            f"| {_fmt(dapper and dapper['rmse_a_mean'])} "
            f"/ {_fmt(dapper and dapper['rmse_a_median'])} "
            f"| {_fmt(row['published_rmse'], 2)} |"
        )
    with_dapper = [row for row in report["rows"] if row.get("dapper")]
    if with_dapper:
        lines += [
            "", "Speed per twin experiment (1001 cycles; speed-up = DAPPER s / ot_filter s; "
            "'vmapped' = all seeds in one compiled program, seconds per seed; 'fast RNG' = the "
            "same code with JAX_THREEFRY_PARTITIONABLE=0):", "",
            "| configuration | DAPPER s | ot_filter s | speed-up | vmapped s/seed | speed-up "
            "| fast RNG s | speed-up | fast RNG vmapped s/seed | speed-up |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for row in with_dapper:
            f, fast = row["float32"], row.get("fast_rng")
            cells = [row["name"], _fmt(row["dapper"]["seconds"], 4), _fmt(f["seconds"], 4),
                     f"{row['speedup']:.1f}x", _fmt(f["batch_seconds_per_seed"], 4),
                     f"{row['speedup_batched']:.1f}x"]
            if fast is not None:
                cells += [_fmt(fast["seconds"], 4), f"{row['speedup_fast_rng']:.1f}x",
                          _fmt(fast["batch_seconds_per_seed"], 4),
                          f"{row['speedup_fast_rng_batched']:.1f}x"]
            else:
                cells += ["–"] * 4
            lines.append("| " + " | ".join(cells) + " |")
        lines += ["", "DAPPER runs one seed at a time on one core; with one process per core "
                  f"({meta['cpu_count']} here) its throughput is at most {meta['cpu_count']}x its "
                  "serial one, so divide the vmapped speed-ups by that for a like-for-like "
                  "throughput comparison."]
    with_cuthbert = [row for row in report["rows"] if row.get("cuthbert")]
    if with_cuthbert:
        lines += ["", f"cuthbert {meta['cuthbert'].get('cuthbert_version', '?')} on the same truths and "
                  "machine (float32; its own scan keeping only the mean, like save_every=0; cuthbert "
                  "also computes the log-likelihood, and on CPU its resampling calls numba on the host):",
                  "", "| configuration | ot_filter s | cuthbert s | cuthbert / ot_filter | ot_filter rmse.a "
                  "mean / median | cuthbert rmse.a mean / median |", "|---|---:|---:|---:|---:|---:|"]
        for row in with_cuthbert:
            c, f = row["cuthbert"], row["float32"]
            lines.append(f"| {row['name']} | {_fmt(f['seconds'], 4)} | {_fmt(c['seconds'], 4)} | "
                         f"{row['cuthbert_ratio']:.1f}x | {_fmt(f['rmse_a_mean'])} / {_fmt(f['rmse_a_median'])} | "
                         f"{_fmt(c['rmse_a_mean'])} / {_fmt(c['rmse_a_median'])} |")
    lines += ["", "Per-seed rmse.a (f32 | f64 on the same observations | DAPPER, own truths):", ""]
    for row in report["rows"]:
        per_seed = " ".join(f"{v:.3f}" for v in row["float32"]["rmse_a"])
        if row.get("float64"):
            per_seed += " | " + " ".join(f"{v:.3f}" for v in row["float64"]["rmse_a"])
        if row.get("dapper"):
            per_seed += " | " + " ".join(f"{v:.3f}" for v in row["dapper"]["rmse_a"])
        lines.append(f"- {row['name']}: {per_seed}")
    divergent = [
        f"{row['name']} {label} {sum(v > 2 * row['published_rmse'] for v in runs['rmse_a'])}/"
        f"{len(runs['rmse_a'])}"
        for row in report["rows"]
        for label, runs in (("f32", row["float32"]), ("f64", row.get("float64")),
                            ("DAPPER", row.get("dapper")))
        if runs and row["published_rmse"] and any(v > 2 * row["published_rmse"] for v in runs["rmse_a"])
    ]
    if divergent:
        lines += ["", "Divergent runs (rmse.a above twice the published value; they dominate "
                  "the mean, not the median): " + ", ".join(divergent) + "."]
    lines += [
        "",
        "ot_filter s: one single-seed twin experiment after compilation (filter over 1001 "
        "observations + rmse.a), median of repeats; compile s: lower + compile of that program. "
        "DAPPER s: xp.assimilate only, error_only stats. rmse.a: mean over analyses t > BurnIn "
        "of the per-analysis RMSE over components.",
        "",
    ]
    return "\n".join(lines)


def build_rows(float32: dict, float64: dict | None, dapper: dict | None,
               cuthbert: dict | None = None, fast_rng: dict | None = None) -> list[dict]:
    rows = []
    for config in CONFIGS:
        row = {
            "name": config.name,
            "experiment": config.experiment,
            "method": config.method,
            "num_particles": config.num_particles,
            "published_rmse": config.published_rmse,
            "analyses_averaged": EXPERIMENTS[config.experiment].analyses_averaged,
            "float32": float32[config.name],
            "speedup": None,
        }
        if float64 is not None:
            row["float64"] = float64[config.name]
        if fast_rng is not None:
            row["fast_rng"] = fast_rng[config.name]
        if dapper is not None and config.name in dapper:
            runs = dapper[config.name]
            if runs["analyses_averaged"] != row["analyses_averaged"]:
                raise RuntimeError(
                    f"{config.name}: DAPPER averages {runs['analyses_averaged']} analyses, "
                    f"this script {row['analyses_averaged']}"
                )
            row["dapper"] = dict(
                runs,
                seconds_all=runs["seconds"],
                seconds=statistics.median(runs["seconds"]),
                rmse_a_mean=float(np.mean(runs["rmse_a"])),
                rmse_a_median=float(np.median(runs["rmse_a"])),
            )
            dapper_seconds = row["dapper"]["seconds"]
            row["speedup"] = dapper_seconds / row["float32"]["seconds"]
            row["speedup_batched"] = dapper_seconds / row["float32"]["batch_seconds_per_seed"]
            if fast_rng is not None:
                row["speedup_fast_rng"] = dapper_seconds / row["fast_rng"]["seconds"]
                row["speedup_fast_rng_batched"] = (
                    dapper_seconds / row["fast_rng"]["batch_seconds_per_seed"])
        if cuthbert is not None and config.name in cuthbert:
            runs = cuthbert[config.name]
            row["cuthbert"] = dict(runs, seconds_all=runs["seconds"], seconds=statistics.median(runs["seconds"]),
                                   rmse_a_mean=float(np.mean(runs["rmse_a"])),
                                   rmse_a_median=float(np.median(runs["rmse_a"])))
            row["cuthbert_ratio"] = row["cuthbert"]["seconds"] / row["float32"]["seconds"]
        rows.append(row)
    return rows


# --------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 seeds, 2 repeats, 1 DAPPER seed")
    parser.add_argument("--seeds", type=int, help="ot_filter truths (default 8, quick 2)")
    parser.add_argument("--repeats", type=int, help="timed runs (default 15, quick 2)")
    parser.add_argument("--dapper-python", help="interpreter with DAPPER 1.7.1 (runs the baseline)")
    parser.add_argument("--dapper-seeds", type=int, help="DAPPER truths (default 8, quick 1)")
    parser.add_argument("--cuthbert-python", help="interpreter with cuthbert (runs its L63 baseline "
                        "on the same truths)")
    parser.add_argument("--no-float64", action="store_true", help="skip the float64 child run")
    parser.add_argument("--no-fast-rng", action="store_true",
                        help="skip the child run timed with JAX_THREEFRY_PARTITIONABLE=0")
    parser.add_argument("--output-dir", type=Path, default=RESULTS)
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    num_seeds = args.seeds or (2 if args.quick else 8)
    repeats = args.repeats or (2 if args.quick else 15)
    dapper_seeds = args.dapper_seeds or (1 if args.quick else 8)

    for experiment in EXPERIMENTS.values():  # the averaging window must match DAPPER's
        averaged = experiment.num_analyses - experiment.burn_in
        assert averaged == experiment.analyses_averaged, (averaged, experiment)

    if args.child is not None:
        with np.load(args.child) as data:
            truths = {name: {"states": data[f"{name}/states"],
                             "observations": data[f"{name}/observations"]}
                      for name in EXPERIMENTS}
        print(json.dumps(measure_ot_filter(truths, repeats)))
        return

    start = time.perf_counter()
    truths = simulate_truths(num_seeds)
    float32 = measure_ot_filter(truths, repeats)
    float64 = fast_rng = None
    with tempfile.TemporaryDirectory() as directory:
        truth_file = Path(directory) / "truths.npz"
        np.savez(truth_file, **{f"{name}/{field}": array
                                for name, truth in truths.items()
                                for field, array in truth.items()})
        if not args.no_float64:
            float64 = run_child(truth_file, repeats, JAX_ENABLE_X64="1")
        if not args.no_fast_rng:
            # JAX's non-partitionable Threefry: other random streams, same distribution; on CPU
            # its bits are several times cheaper (the partitionable default pays for sharding).
            fast_rng = run_child(truth_file, repeats, JAX_THREEFRY_PARTITIONABLE="0")
    dapper = run_dapper(args.dapper_python, dapper_seeds) if args.dapper_python else None
    cuthbert = run_cuthbert(args.cuthbert_python, truths, num_seeds, repeats) if args.cuthbert_python else None

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
        "seeds": num_seeds,
        "repeats": repeats,
        "truth_seed": TRUTH_SEED,
        "filter_seed": FILTER_SEED,
    }
    if dapper is not None:
        dapper_meta = dapper.pop("_meta")
        meta.update(dapper=dapper_meta["dapper"], dapper_numpy=dapper_meta["numpy"],
                    dapper_stats=dapper_meta["stats"], dapper_seeds=len(dapper_meta["seeds"]))
    if cuthbert is not None:
        meta.update(cuthbert=cuthbert.pop("_meta"))
    meta["total_seconds"] = time.perf_counter() - start
    report = {"meta": meta, "rows": build_rows(float32, float64, dapper, cuthbert, fast_rng)}

    args.output_dir.mkdir(parents=True, exist_ok=True)
    markdown = markdown_report(report)
    (args.output_dir / "lorenz_twin.json").write_text(json.dumps(report, indent=1) + "\n")
    (args.output_dir / "lorenz_twin.md").write_text(markdown)
    print(markdown)


if __name__ == "__main__":
    main()
