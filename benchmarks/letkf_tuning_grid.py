"""Tuning the LETKF: an inflation x localisation-radius grid as ONE vmapped program.

Run (from the repository root):

    PYTHONPATH=. python benchmarks/letkf_tuning_grid.py            # 8 x 8 grid, 2 truths
    PYTHONPATH=. python benchmarks/letkf_tuning_grid.py --quick    # 4 x 4, 1 truth

Lorenz-96 as DAPPER's sakov2008 (n = 40, all observed, R = I, 1001 analyses, rmse.a over the
last 601) with the LETKF at N = 7 and random rotations. The inflation and the radius are traced
numbers of the update (``letkf(localisation(geometry, radius, max_radius=...), inflation)``):
``jax.vmap`` over both (and over the truths) compiles one program for the whole grid; a second
grid of new values reuses it (checked: the number of compilations stays the same).

Results: ``benchmarks/results/letkf_tuning_grid.{md,json,png}`` (a heat map of rmse.a, the best
cell and DAPPER's published tuning marked).
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
import time

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter as otf
from ot_filter.experiments.twin_configurations import TWIN_EXPERIMENTS

HERE = os.path.dirname(os.path.abspath(__file__))
NUM_PARTICLES = 7
MAX_RADIUS = 8.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seeds", type=int, default=2)
    args = parser.parse_args()
    if args.quick:
        inflations = np.array([1.0, 1.02, 1.04, 1.08])
        radii = np.array([1.0, 2.0, 4.0, 8.0])
        args.seeds = 1
    else:
        inflations = np.array([1.0, 1.01, 1.02, 1.04, 1.06, 1.08, 1.12, 1.2])
        radii = np.array([0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0])
    experiment = TWIN_EXPERIMENTS["lorenz96"]
    model = experiment.make_model()
    geometry = model.geometry
    burn_in = experiment.burn_in
    truth_keys = jax.random.split(jax.random.key(96), args.seeds)
    states, observations = jax.vmap(
        lambda key: otf.simulate(key, model, experiment.num_analyses))(truth_keys)

    def rmse_a(inflation, radius, key, states, observations):
        update = otf.letkf(otf.localisation(geometry, radius, max_radius=MAX_RADIUS),
                           inflation=inflation, rotate=True)
        result = otf.run_filter(key, model, update, observations, NUM_PARTICLES, save_every=0)
        return jnp.mean(otf.metrics.rmse(result.mean, states)[burn_in:])

    over_truths = jax.vmap(rmse_a, in_axes=(None, None, 0, 0, 0))
    over_radii = jax.vmap(over_truths, in_axes=(None, 0, None, None, None))
    grid = jax.jit(jax.vmap(over_radii, in_axes=(0, None, None, None, None)))
    filter_keys = jax.random.split(jax.random.key(7), args.seeds)
    arguments = (jnp.asarray(inflations, jnp.float32), jnp.asarray(radii, jnp.float32),
                 filter_keys, states, observations)
    started = time.perf_counter()
    values = np.asarray(jax.block_until_ready(grid(*arguments)))  # [inflation, radius, seed]
    first_seconds = time.perf_counter() - started  # compilation + run
    compilations = grid._cache_size()
    # A new grid of values: the same compiled program (no retrace, no recompilation).
    started = time.perf_counter()
    jax.block_until_ready(grid(arguments[0] + 0.005, arguments[1] * 0.9, *arguments[2:]))
    run_seconds = time.perf_counter() - started
    compile_seconds = first_seconds - run_seconds
    recompiled = grid._cache_size() - compilations
    mean = values.mean(axis=-1)
    best = np.unravel_index(np.nanargmin(np.where(np.isfinite(mean), mean, np.inf)), mean.shape)
    meta = dict(date=time.strftime("%Y-%m-%d %H:%M"), platform=platform.platform(), cpus=os.cpu_count(),
                jax=jax.__version__, seeds=args.seeds, num_particles=NUM_PARTICLES,
                runs=int(values.size), compile_seconds=round(compile_seconds, 2),
                run_seconds=round(run_seconds, 2), recompilations_for_a_new_grid=int(recompiled),
                best=dict(inflation=float(inflations[best[0]]), radius=float(radii[best[1]]),
                          rmse=float(mean[best])))
    output = os.path.join(HERE, "results", "letkf_tuning_grid")
    with open(output + ".json", "w") as handle:
        json.dump(dict(meta=meta, inflations=inflations.tolist(), radii=radii.tolist(),
                       rmse=values.tolist()), handle, indent=1)
    lines = [
        "# LETKF tuning grid on Lorenz-96 (sakov2008), one vmapped program",
        "",
        f"{meta['date']}; {meta['platform']}; {meta['cpus']} CPUs; JAX {meta['jax']}. N = "
        f"{NUM_PARTICLES}, rotation on, Gaspari-Cohn taper; {args.seeds} truth(s) x "
        f"{len(inflations)} inflations x {len(radii)} radii = {values.size} twin experiments of "
        f"{experiment.num_analyses} cycles in one program: compile about {compile_seconds:.1f} s, run "
        f"{run_seconds:.1f} s ({1e3 * run_seconds / values.size / experiment.num_analyses:.3f} ms "
        f"per cycle per experiment). A second grid of new values: {recompiled} recompilation(s).",
        "",
        "rmse.a (mean over truths; rows inflation, columns radius):",
        "",
        "| inflation \\ radius | " + " | ".join(f"{r:g}" for r in radii) + " |",
        "|---|" + "--:|" * len(radii),
    ]
    for i, inflation in enumerate(inflations):
        lines.append(f"| {inflation:g} | " + " | ".join(
            f"**{v:.3f}**" if (i, j) == best else f"{v:.3f}" for j, v in enumerate(mean[i])) + " |")
    spread = seed_to_seed_std()
    lines += ["", f"Best: inflation {meta['best']['inflation']:g}, radius {meta['best']['radius']:g}, "
              f"rmse.a {meta['best']['rmse']:.3f}. DAPPER's published tuning: inflation 1.04, "
              "radius 4, rmse.a 0.22."]
    if spread is not None:
        floor = spread / np.sqrt(args.seeds)
        lines += [f"Monte-Carlo floor: the seed-to-seed standard deviation of rmse.a at DAPPER's "
                  f"tuning is {spread:.4f} (8 truths, benchmarks/results/letkf_dapper_sakov2008.json), "
                  f"so a mean over {args.seeds} truth(s) is uncertain by {floor:.4f}: differences "
                  f"below about {2 * floor:.3f} between cells are noise."]
    with open(output + ".md", "w") as handle:
        handle.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    plot(output, inflations, radii, mean, best)


def seed_to_seed_std():
    """Standard deviation over truths of the LETKF's rmse.a at DAPPER's tuning, if measured."""
    path = os.path.join(HERE, "results", "letkf_dapper_sakov2008.json")
    if not os.path.exists(path):
        return None
    rows = json.load(open(path))["rows"]
    values = [row["rmse"] for row in rows if row["method"].startswith("LETKF")]
    return float(np.std(values[0], ddof=1)) if values else None


def plot(output, inflations, radii, mean, best):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    figure, axis = plt.subplots(figsize=(7.5, 6.0))
    shown = np.where(np.isfinite(mean), mean, np.nan)
    image = axis.imshow(shown, origin="lower", cmap="viridis_r", aspect="auto",
                        norm=LogNorm(vmin=max(np.nanmin(shown), 0.1), vmax=max(np.nanmax(shown), 1.0)))
    for i in range(len(inflations)):
        for j in range(len(radii)):
            value = mean[i, j]
            axis.text(j, i, f"{value:.2f}" if np.isfinite(value) else "nan", ha="center",
                      va="center", fontsize=7, color="white" if value > 0.5 else "black")
    axis.add_patch(plt.Rectangle((best[1] - 0.5, best[0] - 0.5), 1, 1, fill=False, ec="red", lw=2,
                                 label="best"))
    if 1.04 in inflations and 4.0 in radii:
        i, j = list(inflations).index(1.04), list(radii).index(4.0)
        axis.plot(j, i - 0.32, marker="v", color="orange", ms=7, ls="none",
                  label="DAPPER's tuning (rmse.a 0.22)")
    axis.set_xticks(range(len(radii)), [f"{r:g}" for r in radii])
    axis.set_yticks(range(len(inflations)), [f"{a:g}" for a in inflations])
    axis.set(xlabel="localisation radius (grid points; Gaspari-Cohn length scale)",
             ylabel="multiplicative inflation",
             title=f"LETKF rmse.a on Lorenz-96 (n = 40, N = {NUM_PARTICLES}), one vmapped program")
    colorbar = figure.colorbar(image, ax=axis, label="rmse.a (observation noise std 1)")
    from matplotlib.ticker import FormatStrFormatter

    for ticks in (colorbar.ax.yaxis.set_major_formatter, colorbar.ax.yaxis.set_minor_formatter):
        ticks(FormatStrFormatter("%.2g"))
    axis.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8, frameon=False)
    figure.tight_layout()
    figure.savefig(output + ".png", dpi=120)


if __name__ == "__main__":
    main()
