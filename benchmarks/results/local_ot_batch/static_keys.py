"""Record of 2026-12-07: local_ot's settings on the chapter's static example, over training keys.

    PYTHONPATH=. python benchmarks/results/local_ot_batch/static_keys.py TAG '{"batch_size": 512}' 10,20,50 [KEYS]

One update (lambda_w = 0.4, y = 1, N = 1000) of the README table's two prior samples (key 2026),
for training keys 0..KEYS-1 (6), each the key the static example gives a method at that place
(``benchmarks/averaged_maps.py``'s draws). The ``default`` rows of ``static_keys.json`` were run
with 0.2.18, whose default was batches of 128: with 0.2.19 pass '{"batch_size": 128}' for them.
PRIOR_KEY=K in the environment draws the two prior samples from key K instead of 2026 (the
held-out check of ``static_keys_prior7.json``).
``local_ot(local_windows(geometry, 0.0), **options)``; AVG=K in the environment averages K
trainings (``averaged_maps``). Prints one JSON row per key (W1 per coordinate to the exact
posterior averaged over the two samples, over the floor of N exact samples averaged the same
way; the worst coordinate over both samples) and a summary per n.
"""
import os, sys, json, time
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax, jax.numpy as jnp
import ot_filter as otf
from ot_filter import metrics
from ot_filter.models import squared_observation
from ot_filter.reference import squared_observation_posterior

NOISE, N = 0.4, 1000
def build(dim, kwargs, avg=1):
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=0.5, static=True)
    update = otf.local_ot(otf.local_windows(model.geometry, 0.0), **kwargs)
    if avg > 1:
        update = otf.averaged_maps(update, avg)
    exact = squared_observation_posterior(1.0, NOISE, scale=0.5)
    y = jnp.ones(dim)
    @jax.jit
    def run(seed_key, place, grid, masses):
        prior_key, update_key, _, floor_key, compare_key = jax.random.split(seed_key, 5)
        prior = jax.vmap(model.sample_initial)(jax.random.split(prior_key, N))
        init_key, apply_key = jax.random.split(jax.random.fold_in(update_key, place))
        post, _, info = update.apply(apply_key, update.init(init_key, prior, model), prior, y, model)
        w1 = lambda s: metrics.compare_to_product_grid(compare_key, s, None, grid, masses, N).w1
        return w1(post), w1(metrics.product_grid_sample(floor_key, grid, masses, N)), info.diverged
    grid = jnp.asarray(exact.grid)
    masses = jnp.broadcast_to(jnp.asarray(exact.density), (dim,) + exact.density.shape)
    return lambda k, p: run(k, p, grid, masses)

tag = sys.argv[1]; kwargs = json.loads(sys.argv[2]); dims = [int(d) for d in sys.argv[3].split(",")]
keys = int(sys.argv[4]) if len(sys.argv) > 4 else 6
avg = int(os.environ.get("AVG", "1"))
for dim in dims:
    run = build(dim, kwargs, avg)
    seeds = jax.random.split(jax.random.key(int(os.environ.get("PRIOR_KEY", "2026"))), 2)
    per_key = []
    for place in range(keys):
        t = time.perf_counter(); vals = []
        for s in range(2):
            w1, fl, div = jax.block_until_ready(run(seeds[s], place))
            vals.append((float(w1.mean()), float(fl.mean()), float(w1.max()), bool(div)))
        w = sum(v[0] for v in vals) / 2; f = sum(v[1] for v in vals) / 2
        per_key.append(w / f)
        print(json.dumps({"tag": tag, "dim": dim, "key": place, "w1": w, "floor": f, "ratio": w / f,
                          "worst": max(v[2] for v in vals), "div": any(v[3] for v in vals), "s": round(time.perf_counter() - t, 1)}), flush=True)
    print(json.dumps({"tag": tag, "dim": dim, "summary": True, "mean": sum(per_key) / len(per_key), "max": max(per_key),
                      "min": min(per_key), "over2": sum(r > 2 for r in per_key)}), flush=True)
