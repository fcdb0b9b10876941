"""LETKF and global EnKFs on Lorenz-96 against DAPPER 1.7.1: same truths, one run.

Run (from the repository root, DAPPER in an interpreter of its own):

    PYTHONPATH=. python benchmarks/letkf_dapper.py --dapper-python /tmp/dapper-venv/bin/python
    PYTHONPATH=. python benchmarks/letkf_dapper.py --setting sparse --seeds 2 ...

1. ``benchmarks/dapper_letkf_baseline.py`` runs in DAPPER's interpreter: it simulates each seed's
   truth and observations with DAPPER's own model file, times ``xp.assimilate`` of each method
   and saves the truths (npz).
2. This process filters exactly those observations with ot_filter (float32, JAX's default) and
   computes rmse.a as DAPPER does: the mean over the analyses with ``masko`` (t > BurnIn) of the
   RMSE over components of the analysis mean against ``xx[kko]``.

Settings and methods (DAPPER's files and the tunings their comments publish):

    sakov2008  all 40 observed, R = I, 0.05 between analyses (1 RK4 step), 1001 analyses
               LETKF(N=7, rot=True, infl=1.04, loc_rad=4)      DAPPER's comment: 0.22
               EnKF('Sqrt', N=7, infl=1.04, rot=True)          (global, N < n: diverges)
    sparse     spantini2019: every second component, R = 0.5 I (variance), 0.4 between
               analyses (20 RK4 steps of 0.02), 2001 analyses
               LETKF(N=40, infl=1.10, loc_rad=4)               1.0
               LETKF(N=100, infl=1.02, loc_rad=4)              0.84
               EnKF('Sqrt', N=40, infl=1.10)                   2.2

ot_filter's LETKF analyses each coordinate with its own taper (DAPPER: batches of 2 coordinates
at their midpoint) and inflates the prior anomalies (DAPPER: the posterior ones); radii have
the same meaning (Gaspari-Cohn half-width sqrt(10/3) radius, DAPPER 1.82 radius).

Timing: ot_filter, one single-seed filter after compilation, median of ``--repeats`` calls,
``save_every=0``; DAPPER, ``xp.assimilate`` only, per seed (its per-step statistics in the
lightest mode, progress bars off). Speed-up = DAPPER seconds per analysis / ot_filter's, both
measured in this run on this machine. Results: ``benchmarks/results/letkf_dapper_<setting>.{md,json}``.
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
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter as otf

HERE = os.path.dirname(os.path.abspath(__file__))

METHODS = {  # setting -> [(DAPPER call, ot_filter builder(model) , N, published rmse.a)]
    "sakov2008": [
        ("LETKF(N=7, rot=True, infl=1.04, loc_rad=4)",
         lambda model: otf.letkf(otf.localisation(model.geometry, 4.0), inflation=1.04, rotate=True),
         7, 0.22),
        ("EnKF('Sqrt', N=7, infl=1.04, rot=True)",
         lambda model: otf.enkf(inflation=1.04, perturbed=False, rotate=True), 7, None),
    ],
    "sparse": [
        ("LETKF(N=40, infl=1.10, loc_rad=4)",
         lambda model: otf.letkf(otf.localisation(model.geometry, 4.0), inflation=1.10), 40, 1.0),
        ("LETKF(N=100, infl=1.02, loc_rad=4)",
         lambda model: otf.letkf(otf.localisation(model.geometry, 4.0), inflation=1.02), 100, 0.84),
        ("EnKF('Sqrt', N=40, infl=1.10)",
         lambda model: otf.enkf(inflation=1.10, perturbed=False), 40, 2.2),
    ],
}


def model_from_truths(truths) -> otf.StateSpaceModel:
    """ot_filter's Lorenz-96 with DAPPER's settings read from the npz."""
    return otf.models.lorenz96(
        dim=int(truths["Nx"]), forcing=float(truths["forcing"]), dt=float(truths["dt"]),
        steps_per_observation=int(truths["dko"]), observed=[int(i) for i in truths["obs_inds"]],
        observation_noise_std=float(np.sqrt(truths["obs_noise_var"])),
        initial_mean=np.asarray(truths["x0_mean"], float),
        initial_std=float(np.sqrt(truths["x0_var"])),
    )


def run_dapper(python: str, setting: str, seeds: int, path: str) -> dict:
    calls = "; ".join(call for call, *_ in METHODS[setting])
    command = [python, os.path.join(HERE, "dapper_letkf_baseline.py"), "--setting", setting,
               "--methods", calls, "--seeds", str(seeds), "--save-truths", path]
    print("running DAPPER:", " ".join(command), file=sys.stderr, flush=True)
    output = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(output.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--setting", choices=sorted(METHODS), default="sakov2008")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dapper-python", default="/tmp/dapper-venv/bin/python")
    parser.add_argument("--truths", default="", help="reuse an npz (then DAPPER is not rerun)")
    parser.add_argument("--dapper-json", default="", help="DAPPER's JSON for --truths")
    args = parser.parse_args()
    started = time.time()

    if args.truths:
        path = args.truths
        dapper = json.load(open(args.dapper_json)) if args.dapper_json else {}
    else:
        path = os.path.join(tempfile.mkdtemp(), f"truths_{args.setting}.npz")
        dapper = run_dapper(args.dapper_python, args.setting, args.seeds, path)
    truths = np.load(path)
    model = model_from_truths(truths)
    xx, yy = truths["xx"], truths["yy"]
    kko, masko = truths["kko"], truths["masko"].astype(bool)
    num_seeds = min(args.seeds, yy.shape[0])
    states = jnp.asarray(xx[:num_seeds, kko], jnp.float32)  # [S, Ko+1, n]
    observations = jnp.asarray(yy[:num_seeds], jnp.float32)
    num_analyses = observations.shape[1]

    rows = []
    for call, build, num_particles, published in METHODS[args.setting]:
        update = build(model)

        @jax.jit
        def twin(key, observations, states, update=update, num_particles=num_particles):
            result = otf.run_filter(key, model, update, observations, num_particles, save_every=0)
            errors = jnp.sqrt(jnp.mean((result.mean - states) ** 2, axis=-1))
            return jnp.sum(jnp.where(masko, errors, 0.0)) / masko.sum()

        keys = jax.random.split(jax.random.key(2026), num_seeds)
        compile_start = time.perf_counter()
        compiled = twin.lower(keys[0], observations[0], states[0]).compile()
        compile_seconds = time.perf_counter() - compile_start
        rmse = [float(compiled(keys[s], observations[s], states[s])) for s in range(num_seeds)]
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(compiled(keys[0], observations[0], states[0]))
            times.append(time.perf_counter() - start)
        seconds = float(np.median(times))
        entry = dapper.get(call, {})
        dapper_rmse = entry.get("rmse_a", [])
        dapper_seconds = entry.get("seconds", [])
        rows.append(dict(
            method=call, num_particles=num_particles, published=published,
            rmse=rmse, dapper_rmse=dapper_rmse, seconds=seconds, compile_seconds=compile_seconds,
            dapper_seconds=dapper_seconds,
            ms_per_analysis=1e3 * seconds / num_analyses,
            dapper_ms_per_analysis=(1e3 * float(np.mean(dapper_seconds)) / num_analyses
                                    if dapper_seconds else None),
        ))
        print(f"{call}: rmse.a {np.mean(rmse):.3f} (DAPPER {np.mean(dapper_rmse) if dapper_rmse else float('nan'):.3f}), "
              f"{rows[-1]['ms_per_analysis']:.3f} ms/analysis", file=sys.stderr, flush=True)

    write_results(args, rows, num_seeds, num_analyses, int(masko.sum()), time.time() - started)


def write_results(args, rows, num_seeds, num_analyses, averaged, elapsed) -> None:
    out = os.path.join(HERE, "results", f"letkf_dapper_{args.setting}")
    meta = dict(date=time.strftime("%Y-%m-%d %H:%M"), platform=platform.platform(),
                cpus=os.cpu_count(), jax=jax.__version__, backend=jax.default_backend(),
                seeds=num_seeds, analyses=num_analyses, averaged=averaged,
                script_seconds=round(elapsed, 1))
    with open(out + ".json", "w") as handle:
        json.dump(dict(meta=meta, rows=rows), handle, indent=1)
    lines = [
        f"# Lorenz-96 {args.setting}: ot_filter against DAPPER 1.7.1, same truths",
        "",
        f"{meta['date']}; {meta['platform']}; {meta['cpus']} CPUs; JAX {meta['jax']} on "
        f"{meta['backend']}; {num_seeds} seeds (DAPPER's truths and observations, filtered by "
        f"both); {num_analyses} analyses, rmse.a over the last {averaged}. Script time "
        f"{meta['script_seconds']} s.",
        "",
        "| method | N | rmse.a ot_filter mean / median | rmse.a DAPPER mean / median | ratio of means "
        "| published | ot_filter ms/analysis | DAPPER ms/analysis | speed-up |",
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for row in rows:
        ours, theirs = np.asarray(row["rmse"]), np.asarray(row["dapper_rmse"])
        theirs_text = f"{theirs.mean():.3f} / {np.median(theirs):.3f}" if theirs.size else "–"
        ratio = f"{ours.mean() / theirs.mean():.3f}" if theirs.size else "–"
        dapper_ms = row["dapper_ms_per_analysis"]
        lines.append(
            f"| {row['method']} | {row['num_particles']} | {ours.mean():.3f} / {np.median(ours):.3f} "
            f"| {theirs_text} | {ratio} | {row['published'] if row['published'] is not None else '–'} "
            f"| {row['ms_per_analysis']:.3f} | {dapper_ms:.2f} | "
            f"{dapper_ms / row['ms_per_analysis']:.1f}x |" if dapper_ms else "| – | – |"
        )
    lines += ["", "Per-seed rmse.a (ot_filter | DAPPER):", ""]
    for row in rows:
        lines.append(f"- {row['method']}: " + " ".join(f"{v:.3f}" for v in row["rmse"]) + " | "
                     + " ".join(f"{v:.3f}" for v in row["dapper_rmse"]))
    lines += ["", "Monte-Carlo floor: the seed-to-seed standard deviation of rmse.a over "
              "the truths, divided by sqrt(seeds), is the uncertainty of each mean:", ""]
    for row in rows:
        for name, values in (("ot_filter", row["rmse"]), ("DAPPER", row["dapper_rmse"])):
            if len(values) > 1:
                lines.append(f"- {row['method']} {name}: {np.std(values, ddof=1) / np.sqrt(len(values)):.4f}")
    with open(out + ".md", "w") as handle:
        handle.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
