"""What averaging K trainings of a map buys on the chapter's static example, over training keys.

    PYTHONPATH=.:benchmarks python benchmarks/averaged_maps.py [--dims 10,20,50]
        [--methods local_ot,local_ot_avg3] [--keys 6] [--first-key 0] [--seeds 2] [--out DIR]

One update (lambda_w = 0.4, y = 1, N = 1000) of the static example's prior samples (key 2026, the
README table's seeds), each method trained with ``--keys`` training keys (from ``--first-key``; runs of
other keys already in ``--out`` are kept and summarised with these): key i is the one the
static example gives the method at place i of its list (so a single-key run there is one of
these). ``<method>_avgK`` is ``averaged_maps(<method>, K)`` (``experiments._common.make_updates``).
Scored by W1 per coordinate to the exact marginals (mean over coordinates, and the worst
coordinate), beside N exact samples (the floor; its worst coordinate too). Writes
``averaged_maps.json`` and ``averaged_maps.md`` to ``--out`` (rows of other dims or methods in an
earlier file are kept).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from ot_filter import metrics  # noqa: E402
from ot_filter.experiments._common import make_updates, write_text_atomic  # noqa: E402
from ot_filter.models import squared_observation  # noqa: E402
from ot_filter.reference import squared_observation_posterior  # noqa: E402

NOISE, NUM_PARTICLES = 0.4, 1000


def build(dim: int, method: str):
    """``run(seed_key, place) -> (w1[dim], floor_w1[dim])``, jitted: the static example's draws
    for that seed and its training key for a method at ``place``."""
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=0.5, static=True)
    update = make_updates([method], None, model=model, radius=0.0)[method]
    exact = squared_observation_posterior(1.0, NOISE, scale=0.5)
    y = jnp.ones(dim)

    @jax.jit
    def run(seed_key, place, grid, masses):  # grid, masses as arguments: not constant-folded
        prior_key, update_key, _, floor_key, compare_key = jax.random.split(seed_key, 5)  # run_static_example's
        prior = jax.vmap(model.sample_initial)(jax.random.split(prior_key, NUM_PARTICLES))
        init_key, apply_key = jax.random.split(jax.random.fold_in(update_key, place))
        posterior, _, info = update.apply(apply_key, update.init(init_key, prior, model), prior, y, model)

        def w1(samples):
            return metrics.compare_to_product_grid(compare_key, samples, None, grid, masses, NUM_PARTICLES).w1

        floor = w1(metrics.product_grid_sample(floor_key, grid, masses, NUM_PARTICLES))
        return w1(posterior), floor, info.diverged

    grid = jnp.asarray(exact.grid)
    masses = jnp.broadcast_to(jnp.asarray(exact.density), (dim,) + exact.density.shape)
    return lambda seed_key, place: run(seed_key, place, grid, masses)


def measure(dim: int, method: str, keys, seeds: int) -> list:
    """One row per (seed, training key in ``keys``)."""
    run = build(dim, method)
    rows = []
    for seed, seed_key in enumerate(jax.random.split(jax.random.key(2026), seeds)):
        for place in keys:
            start = time.perf_counter()
            w1, floor, diverged = jax.block_until_ready(run(seed_key, place))
            rows.append({"seed": seed, "key": place, "w1": float(w1.mean()), "w1_max": float(w1.max()),
                         "floor": float(floor.mean()), "floor_max": float(floor.max()),
                         "diverged": bool(diverged), "seconds": round(time.perf_counter() - start, 1)})
            print(dim, method, json.dumps(rows[-1]), flush=True)
    return rows


def summarise(dim: int, method: str, rows: list) -> dict:
    """The record of every run of one (n, method), those of earlier invocations included."""
    keys = sorted({r["key"] for r in rows})
    ratios = np.array([row["w1"] / row["floor"] for row in rows])
    # The README's cell: a key's W1 averaged over the seeds, over the floor averaged over them.
    per_key = np.array([np.mean([r["w1"] for r in rows if r["key"] == k]) for k in keys])
    floor = np.mean([r["floor"] for r in rows if r["key"] == keys[0]])
    return {"dim": dim, "method": method, "keys": len(keys), "seeds": len({r["seed"] for r in rows}), "runs": rows,
            "floor": float(floor), "w1_mean": float(per_key.mean()),
            "cell_ratio_mean": float(per_key.mean() / floor), "cell_ratio_min": float(per_key.min() / floor),
            "cell_ratio_max": float(per_key.max() / floor),
            "run_ratio_max": float(ratios.max()), "w1_max_mean": float(np.mean([r["w1_max"] for r in rows])),
            "floor_max_mean": float(np.mean([r["floor_max"] for r in rows if r["key"] == keys[0]])),
            "diverged": int(sum(r["diverged"] for r in rows)),
            "seconds_per_update": float(np.median([r["seconds"] for r in rows]))}


def table(records) -> str:
    lines = ["# Averaged maps on the static example (one update, N = 1000)", "",
             "W1 per coordinate to the exact posterior over the floor of N exact samples. A cell is one training",
             "key's W1 averaged over the seeds (the README table's cell); mean, best and worst over the keys.",
             "Worst run: one key on one seed. Worst coordinate: mean over runs.", "",
             "| n | method | keys x seeds | W1 (mean) | / floor: mean | best key | worst key | worst run | worst coordinate (floor) | fallbacks | s / update |",
             "|--:|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
    for r in sorted(records, key=lambda r: (r["dim"], r["method"])):
        lines.append(f"| {r['dim']} | {r['method']} | {r['keys']} x {r['seeds']} | {r['w1_mean']:.4f} | "
                     f"{r['cell_ratio_mean']:.2f} | {r['cell_ratio_min']:.2f} | {r['cell_ratio_max']:.2f} | "
                     f"{r['run_ratio_max']:.2f} | {r['w1_max_mean']:.3f} ({r['floor_max_mean']:.3f}) | "
                     f"{r['diverged']} | {r['seconds_per_update']:.0f} |")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dims", default="10,20,50")
    parser.add_argument("--methods", default="local_ot,local_ot_avg3")
    parser.add_argument("--keys", type=int, default=6)
    parser.add_argument("--first-key", type=int, default=0, help="training keys first-key .. first-key + keys - 1")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/results/averaged_maps")
    args = parser.parse_args()
    path = os.path.join(args.out, "averaged_maps.json")
    records = json.load(open(path)) if os.path.exists(path) else []
    for dim in (int(d) for d in args.dims.split(",")):
        for method in args.methods.split(","):
            rows = measure(dim, method, range(args.first_key, args.first_key + args.keys), args.seeds)
            # a rerun replaces its (seed, key) rows and keeps the others (keys run elsewhere)
            earlier = [r for r in records if (r["dim"], r["method"]) == (dim, method)]
            fresh = {(r["seed"], r["key"]) for r in rows}
            rows = [r for rec in earlier for r in rec["runs"] if (r["seed"], r["key"]) not in fresh] + rows
            records = [r for r in records if (r["dim"], r["method"]) != (dim, method)] + [summarise(dim, method, rows)]
            os.makedirs(args.out, exist_ok=True)
            write_text_atomic(path, json.dumps(records, indent=1))
            write_text_atomic(os.path.join(args.out, "averaged_maps.md"), table(records))
    print(table(records))


if __name__ == "__main__":
    main()
