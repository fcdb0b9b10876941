"""Where the global map's plateau at n = 10 comes from: the particles it learns from, or the map.

    PYTHONPATH=. python benchmarks/ot_sample_size.py --train 1000 [--dim 10] [--seeds 2]
        [--evaluate 10000] [--options '{}'] [--out FILE]

Static example (lambda_w = 0.4, y = 1). One global ``ot()`` update (its defaults unless
``--options``) is trained on ``--train`` prior particles, as a filter would train it. It is then
scored two ways, by W1 per coordinate to the exact posterior (mean over coordinates, and the worst
one), each beside the W1 of as many exact samples (the Monte-Carlo floor at that size):

- in sample: the update's own output, its ``--train`` particles transported (what the static
  example and the filters score);
- out of sample: ``--evaluate`` fresh prior particles transported by the same trained map
  (``update.transport``), whose floor is small (about 0.011 at 10,000): what is left above it is
  the map's own error;
- leakage: the exact map's coordinate k reads (x_k, y_k) alone. Holding each fresh particle's x_k
  and redrawing its other coordinates from the prior (``--redraws`` times), ``leakage_std`` is
  how much T_k moves (root mean over particles of its variance over the redraws), and
  ``others_averaged`` the W1 of T_k averaged over the redraws (a map of x_k alone, the leakage
  removed) against the same exact marginal.

If the map learned from 1,000 particles is as good out of sample as one learned from 10,000 or
100,000 (the training cost does not grow with N: the mini-batches keep their size), the plateau is
the optimisation's or the network's; if more particles bring it down, it is the estimation from N
samples. Seeds come from key 2026, split otherwise than in ``benchmarks/ot_sizes.py``: other prior
samples than its records. Appends one record per run
to ``--out`` (JSON list).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter as otf
from ot_filter import metrics
from ot_filter.experiments._common import write_text_atomic
from ot_filter.models import squared_observation
from ot_filter.reference import squared_observation_posterior

NOISE, SCALE, OBSERVATION = 0.4, 0.5, 1.0


def exact_scoring(dim):
    """``(w1, exact_samples)``: ``w1(samples[M, dim]) -> [dim]``, W1 per coordinate to the exact
    marginal's CDF; ``exact_samples(key, num) -> [num, dim]`` from the exact posterior."""
    exact = squared_observation_posterior(OBSERVATION, NOISE, scale=SCALE)
    grid = jnp.asarray(exact.grid)
    cdf = jnp.cumsum(exact.density) / jnp.sum(exact.density)

    def w1(samples):
        return jax.vmap(lambda column: metrics.wasserstein_1d(column, grid, cdf), in_axes=1)(samples)

    def exact_samples(key, num):
        masses = jnp.broadcast_to(exact.density, (dim,) + exact.density.shape)
        return metrics.product_grid_sample(key, grid, masses, num)

    return w1, exact_samples


class Draws(NamedTuple):
    """What one seed's key draws (``draws``)."""

    init_key: jax.Array
    apply_key: jax.Array
    floor_key: jax.Array  # the in-sample floor's exact samples
    floor2_key: jax.Array  # the out-of-sample floor's
    redraw_key: jax.Array
    prior: jax.Array  # [num_train, dim] the particles the map learns from
    fresh: jax.Array  # [num_evaluate, dim] fresh prior particles it is scored on
    simulated: jax.Array  # [num_evaluate, dim] their simulated observations


def draws(key, model, num_train, num_evaluate) -> Draws:
    """The seed's keys, prior sample and fresh particles (``benchmarks/ot_training_curve.py``
    draws the same)."""
    prior_key, init_key, apply_key, fresh_key, floor_key, floor2_key, redraw_key = jax.random.split(key, 7)
    prior = jax.vmap(model.sample_initial)(jax.random.split(prior_key, num_train))
    state_key, observation_key = jax.random.split(fresh_key)
    fresh = jax.vmap(model.sample_initial)(jax.random.split(state_key, num_evaluate))
    simulated = jax.vmap(model.sample_observation)(jax.random.split(observation_key, num_evaluate), fresh)
    return Draws(init_key, apply_key, floor_key, floor2_key, redraw_key, prior, fresh, simulated)


def build(*, dim, num_train, num_evaluate, options, num_redraws):
    """The compiled run of one seed: key -> per-coordinate W1s (one program for all seeds)."""
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=SCALE, static=True)
    update = otf.ot(**options)
    w1, exact_samples = exact_scoring(dim)
    y = jnp.full((dim,), OBSERVATION)

    @jax.jit
    def go(key):
        d = draws(key, model, num_train, num_evaluate)
        fresh, simulated = d.fresh, d.simulated
        state = update.init(d.init_key, d.prior, model)
        posterior, state, info = update.apply(d.apply_key, state, d.prior, y, model)
        moved = update.transport(state, fresh, y, simulated)

        # The exact map's coordinate k reads (x_k, y_k) only. Hold x_k, redraw the other coordinates
        # from the prior (num_redraws times), and see how much T_k moves (leakage), and how far
        # its average over the redraws, a map of x_k alone, is from the exact marginal.
        def redraw(key):
            others = jax.vmap(model.sample_initial)(jax.random.split(key, num_evaluate))

            def coordinate(k):
                mixed = others.at[:, k].set(fresh[:, k])
                return update.transport(state, mixed, y, simulated)[:, k]

            return jax.lax.map(coordinate, jnp.arange(dim)).T  # [M, dim]

        redrawn = jax.lax.map(redraw, jax.random.split(d.redraw_key, num_redraws))  # [R, M, dim]
        leakage = jnp.sqrt(jnp.mean(jnp.var(redrawn, axis=0), axis=0))  # [dim]
        return {"in_sample": w1(posterior), "floor_in_sample": w1(exact_samples(d.floor_key, num_train)),
                "out_of_sample": w1(moved), "floor_out_of_sample": w1(exact_samples(d.floor2_key, num_evaluate)),
                "others_averaged": w1(jnp.mean(redrawn, axis=0)), "leakage_std": leakage,
                "diverged": info.diverged}

    return go


def run_one(go, seed_key):
    start = time.perf_counter()
    out = jax.block_until_ready(go(seed_key))
    seconds = time.perf_counter() - start
    record = {name: float(np.mean(value)) for name, value in out.items() if name != "diverged"}
    record.update({name + "_worst": float(np.max(value)) for name, value in out.items() if name != "diverged"})
    record["diverged"] = bool(out["diverged"])
    record["seconds"] = round(seconds, 1)
    return record


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dim", type=int, default=10)
    parser.add_argument("--train", type=int, required=True, help="prior particles the map learns from")
    parser.add_argument("--evaluate", type=int, default=10_000, help="fresh particles it is scored on")
    parser.add_argument("--options", default="{}", help="ot() options as JSON")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--redraws", type=int, default=16, help="draws of the other coordinates (leakage)")
    parser.add_argument("--out", default="benchmarks/results/ot_dimension_size_rule/sample_size.json")
    args = parser.parse_args()
    options = json.loads(args.options)
    go = build(dim=args.dim, num_train=args.train, num_evaluate=args.evaluate, options=options,
               num_redraws=args.redraws)
    seeds = []
    for seed, seed_key in enumerate(jax.random.split(jax.random.key(2026), args.seeds)):
        record = run_one(go, seed_key)  # the first seed's seconds include compiling
        print(json.dumps({"seed": seed, **record}), flush=True)
        seeds.append(record)
    record = {"dim": args.dim, "train": args.train, "evaluate": args.evaluate, "options": options,
              "per_seed": seeds, "device": str(jax.devices()[0])}
    for name in ("in_sample", "floor_in_sample", "out_of_sample", "floor_out_of_sample", "others_averaged",
                 "leakage_std"):
        values = np.array([s[name] for s in seeds])
        record[name] = float(values.mean())
        record[name + "_se"] = float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else None
    print(json.dumps({k: v for k, v in record.items() if k != "per_seed"}), flush=True)
    records = json.load(open(args.out)) if os.path.exists(args.out) else []
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    write_text_atomic(args.out, json.dumps(records + [record], indent=1))


if __name__ == "__main__":
    main()
