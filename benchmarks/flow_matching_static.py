"""The flow-matching update against the chapter's static example, over training keys.

    PYTHONPATH=. python benchmarks/flow_matching_static.py TAG '{json options}' 2,10,20,50 [KEYS] [--ot]

One update (lambda_w = 0.4, y = 1, N = 1000) of the README table's two prior samples (key 2026;
PRIOR_KEY=K in the environment draws two others), for training keys 0..KEYS-1 (3; FIRST_KEY=k in the environment starts at k), each the key
the static example gives a method at that place (as ``benchmarks/averaged_maps.py`` and
``benchmarks/results/local_ot_batch/static_keys.py``, so that the places match their records).
``flow_matching(**options)``, or with ``--local`` ``local_flow(local_windows(ring(n), 0, 0), **options)``
(each coordinate its own window and observation); ``--local-ot`` adds ``local_ot()`` on the same
windows with its defaults; with ``--ot`` the global ``ot()`` with its defaults runs on the same
samples and keys, in the same process, for a ratio of seconds measured in one run. Prints one JSON
row per (method, n, key): W1 per coordinate to the exact posterior averaged over the two samples,
the floor of N exact samples scored the same way, their ratio, the worst coordinate over both
samples and its floor, the joint energy distance to N exact samples and its floor, whether the
update fell back, and the seconds (both samples, after a first call that compiled).
"""
import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax
import jax.numpy as jnp

import ot_filter as otf
from ot_filter import metrics
from ot_filter.models import squared_observation
from ot_filter.reference import squared_observation_posterior

NOISE, N = 0.4, 1000


def build(dim, update):
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=0.5, static=True)
    exact = squared_observation_posterior(1.0, NOISE, scale=0.5)
    y = jnp.ones(dim)

    @jax.jit
    def run(seed_key, place, grid, masses):
        prior_key, update_key, _, floor_key, compare_key = jax.random.split(seed_key, 5)
        prior = jax.vmap(model.sample_initial)(jax.random.split(prior_key, N))
        init_key, apply_key = jax.random.split(jax.random.fold_in(update_key, place))
        post, _, info = update.apply(apply_key, update.init(init_key, prior, model), prior, y, model)
        score = lambda s: metrics.compare_to_product_grid(compare_key, s, None, grid, masses, N)
        return score(post), score(metrics.product_grid_sample(floor_key, grid, masses, N)), info.diverged

    grid = jnp.asarray(exact.grid)
    masses = jnp.broadcast_to(jnp.asarray(exact.density), (dim,) + exact.density.shape)
    return lambda k, p: run(k, p, grid, masses)


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    tag, options, dims = args[0], json.loads(args[1]), [int(d) for d in args[2].split(",")]
    keys = int(args[3]) if len(args) > 3 else 3
    if "--local" in sys.argv:  # the localised flow, told that the coordinates are independent
        methods = {"local_flow": lambda dim: otf.local_flow(otf.local_windows(otf.ring(dim), 0, 0), **options)}
    else:
        methods = {"flow_matching": lambda dim: otf.flow_matching(**options)}
    if "--ot" in sys.argv:
        methods["ot"] = lambda dim: otf.ot()
    if "--local-ot" in sys.argv:  # the localised OT update with its defaults, same windows
        methods["local_ot"] = lambda dim: otf.local_ot(otf.local_windows(otf.ring(dim), 0, 0))
    seeds = jax.random.split(jax.random.key(int(os.environ.get("PRIOR_KEY", "2026"))), 2)
    for dim in dims:
        for name, update in methods.items():
            run = build(dim, update(dim))
            if not os.environ.get("NO_WARMUP"):  # NO_WARMUP=1: the first row's seconds include compiling
                jax.block_until_ready(run(seeds[0], 0))  # compile
            for place in range(int(os.environ.get("FIRST_KEY", "0")), keys):
                start = time.perf_counter()
                rows = [jax.block_until_ready(run(seeds[s], place)) for s in range(2)]
                seconds = time.perf_counter() - start
                w1 = sum(float(r[0].w1.mean()) for r in rows) / 2
                floor = sum(float(r[1].w1.mean()) for r in rows) / 2
                print(json.dumps({
                    "tag": tag, "method": name, "dim": dim, "key": place, "options": options if name not in ("ot", "local_ot") else {},
                    "w1": w1, "floor": floor, "ratio": w1 / floor,
                    "worst": max(float(r[0].w1.max()) for r in rows),
                    "worst_floor": max(float(r[1].w1.max()) for r in rows),
                    "energy": sum(float(r[0].energy) for r in rows) / 2,
                    "energy_floor": sum(float(r[1].energy) for r in rows) / 2,
                    "diverged": any(bool(r[2]) for r in rows), "s": round(seconds, 1),
                }), flush=True)


if __name__ == "__main__":
    main()
