"""Diagnostic (issue 17): the static example at n = 10, the global ot() defaults trained K times on the
same prior sample (other training keys); the K transported ensembles averaged particle by particle
(the output of the average of the K maps), scored by W1 to the exact marginals, in sample (the
1,000 particles the maps learn from) and out of sample (10,000 fresh ones). The prior samples are
``benchmarks/ot_sample_size.py``'s (key 2026).

    PYTHONPATH=.:benchmarks python benchmarks/results/ot_dimension_size_rule/trainings_averaged.py 3
"""
import json, os, sys, time
import jax, jax.numpy as jnp, numpy as np
import ot_filter as otf
from ot_sample_size import exact_scoring, draws, NOISE, SCALE, OBSERVATION
from ot_filter.models import squared_observation
dim, K = 10, int(sys.argv[1])
model = squared_observation(dim=dim, noise=NOISE, observation_scale=SCALE, static=True)
update = otf.ot()
w1, exact_samples = exact_scoring(dim)
y = jnp.full((dim,), OBSERVATION)

@jax.jit
def one(key, prior, fresh, simulated):
    init_key, apply_key = jax.random.split(key)
    state = update.init(init_key, prior, model)
    posterior, state, info = update.apply(apply_key, state, prior, y, model)
    return posterior, update.transport(state, fresh, y, simulated), info.diverged

out = []
for seed, seed_key in enumerate(jax.random.split(jax.random.key(2026), 2)):
    d = draws(seed_key, model, 1000, 10_000)
    runs = []
    for k in range(K):
        t = time.perf_counter()
        runs.append(jax.block_until_ready(one(jax.random.fold_in(d.init_key, k), d.prior, d.fresh, d.simulated)))
        print(seed, k, "s", round(time.perf_counter() - t), "in", float(np.mean(w1(runs[-1][0]))), "out", float(np.mean(w1(runs[-1][1]))), "div", bool(runs[-1][2]), flush=True)
    rec = {"seed": seed, "single_in": [float(np.mean(w1(r[0]))) for r in runs], "single_out": [float(np.mean(w1(r[1]))) for r in runs],
           "floor_in": float(np.mean(w1(exact_samples(d.floor_key, 1000)))), "floor_out": float(np.mean(w1(exact_samples(d.floor2_key, 10_000))))}
    for j in range(2, K + 1):
        rec[f"average{j}_in"] = float(np.mean(w1(sum(r[0] for r in runs[:j]) / j)))
        rec[f"average{j}_out"] = float(np.mean(w1(sum(r[1] for r in runs[:j]) / j)))
        rec[f"average{j}_in_worst"] = float(np.max(w1(sum(r[0] for r in runs[:j]) / j)))
    print(json.dumps(rec), flush=True)
    out.append(rec)
    json.dump(out, open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "two_and_three_trainings_averaged.json"), "w"), indent=1)
