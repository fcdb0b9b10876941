"""What a step of the localised OT filter with an offline map costs, used as is ((a): no
training online), against the EnKF's step on the same problem, in one run.

    PYTHONPATH=.:benchmarks python benchmarks/local_amortised_cost.py [--dims 10,50] [--widths 64,32]

The dynamic example (coordinates observed one by one, windows of radius 0), N = 1000, 5
simulations of 20 steps vmapped, median of 5 timed runs after compilation. The map's values do
not change its cost, so untrained maps of each width are timed (``amortised_local_ot`` of a
``LocalMapConfig``'s initial parameters). Rows: the whole filter, (a) with T tabulated at each
of ``--knots`` knots a window (``map_knots``; 0: T at every particle), (a) without the prior
context (``prior_context=0``, default knots), and the forward pass of T over the N n windows
alone.
Appends to ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import ot_filter as otf
from ot_filter.amortised import LocalMap, LocalMapConfig, amortised_local_ot
from ot_filter.experiments._common import simulate_truths, write_text_atomic
from ot_filter.experiments.dynamic_example import dynamic_model
from ot_filter.experiments.local_amortised import local_map_config
from ot_filter.updates.ot import networks

PARTICLES, STEPS, SIMULATIONS, REPEATS = 1000, 20, 5, 5


def timed(function, *args):
    compiled = jax.jit(function).lower(*args).compile()
    jax.block_until_ready(compiled(*args))
    seconds = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        seconds.append(time.perf_counter() - start)
    return float(np.median(seconds))


def untrained(config: LocalMapConfig, model) -> LocalMap:
    prior = jnp.zeros((PARTICLES, config.state_dim)) + jax.random.normal(jax.random.key(0), (PARTICLES, config.state_dim))
    params = amortised_local_ot(config, model).init(jax.random.key(1), prior, model).training.params
    return LocalMap(params, config, {})


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dims", default="10,50")
    parser.add_argument("--widths", default="64,32")
    parser.add_argument("--knots", default="128,256,0", help="map_knots of (a) (0: T at every particle)")
    parser.add_argument("--out", default="benchmarks/results/amortised_ot/local_cost.json")
    args = parser.parse_args()
    records = []
    for dim in (int(d) for d in args.dims.split(",")):
        model = dynamic_model(dim)
        _, observations = simulate_truths(jax.random.key(0), model, STEPS, SIMULATIONS)
        keys = jax.random.split(jax.random.key(1), SIMULATIONS)

        def filter_seconds(update):
            return timed(jax.vmap(lambda k, y: otf.run_filter(k, model, update, y, PARTICLES).mean), keys,
                         observations)

        row = {"dim": dim, "enkf": filter_seconds(otf.enkf())}
        for width in (int(w) for w in args.widths.split(",")):
            config = local_map_config(dim)._replace(width=width)
            for knots in (int(k) for k in args.knots.split(",")):
                row[f"a_width{width}_knots{knots}"] = filter_seconds(
                    amortised_local_ot(untrained(config, model), model, map_knots=knots))
            bare = config._replace(prior_context=0)
            row[f"a_width{width}_no_quantiles"] = filter_seconds(amortised_local_ot(untrained(bare, model), model))
            local_map = untrained(config, model)
            _, transport_net = networks(local_ot_structure(local_map, model))
            inputs = jax.random.normal(jax.random.key(2), (SIMULATIONS * STEPS, PARTICLES * dim, 1))
            conditioning = jax.random.normal(jax.random.key(3), inputs.shape[:2] + (2 + 8,))
            row[f"forward_width{width}"] = timed(
                jax.vmap(lambda x, y: transport_net.apply(local_map.params.transport, x, y)), inputs, conditioning)
        print({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()},
              {k: round(v / row["enkf"], 1) for k, v in row.items() if k != "dim"}, flush=True)
        records.append(row)
    previous = json.load(open(args.out)) if os.path.exists(args.out) else []
    write_text_atomic(args.out, json.dumps(previous + [{"setting": vars(args), "rows": records}], indent=1))


def local_ot_structure(local_map, model):
    from ot_filter.updates.local_ot import local_update_parts

    return local_update_parts(amortised_local_ot(local_map, model))[1]


if __name__ == "__main__":
    main()
