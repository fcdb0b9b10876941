import sys, json
import numpy as np, jax, jax.numpy as jnp
sys.path[:0] = [".", "benchmarks"]
from ot_sample_size import exact_scoring
w1, _ = exact_scoring(10)
w1 = jax.jit(w1)
def score(x): return float(np.mean(w1(jnp.asarray(x)))), float(np.max(w1(jnp.asarray(x))))
def share(x): return float(np.mean(np.abs((x > 0).mean(0) - 0.5)))
def mixture(stack):  # stack [K, M, n]: particle i from member i mod K
    K, M = stack.shape[:2]
    return stack[np.arange(M) % K, np.arange(M)]
res = {}
for seed in (0, 1):
    d = np.load(f"seed{seed}.npz")
    own, fresh = d["own"], d["fresh"]  # [keys, checkpoints(11: 5000..10000), M, n]
    r = {"floor_in": float(d["floor_in"]), "floor_out": float(d["floor_out"]),
         "prior_share": share(d["prior"])}
    r["final_single"] = [score(own[k, -1]) for k in range(own.shape[0])]
    r["final_single_fresh"] = [score(fresh[k, -1])[0] for k in range(own.shape[0])]
    r["final_single_share"] = [share(own[k, -1]) for k in range(own.shape[0])]
    for K, step in ((2, 2), (4, 2), (4, 1), (6, 2), (11, 1)):
        idx = list(range(10, 10 - K * step, -step))
        if min(idx) < 0: continue
        r[f"ckpt_mix{K}x{step*500}"] = [score(mixture(own[k, idx])) for k in range(own.shape[0])]
        r[f"ckpt_mix{K}x{step*500}_fresh"] = [score(mixture(fresh[k, idx]))[0] for k in range(own.shape[0])]
        r[f"ckpt_avg{K}x{step*500}"] = [score(own[k, idx].mean(0)) for k in range(own.shape[0])]
        r[f"ckpt_mix{K}x{step*500}_share"] = [share(mixture(own[k, idx])) for k in range(own.shape[0])]
    r["trainings_mix3"] = score(mixture(own[:, -1])); r["trainings_mix3_fresh"] = score(mixture(fresh[:, -1]))[0]
    r["trainings_avg3"] = score(own[:, -1].mean(0)); r["trainings_avg3_fresh"] = score(fresh[:, -1].mean(0))[0]
    r["trainings_mix3_share"] = share(mixture(own[:, -1]))
    allk = own[:, [10, 8, 6, 4]].reshape(-1, *own.shape[2:])
    r["trainings3_x_ckpt4_mix"] = score(mixture(allk))
    res[seed] = r
    print(seed, {k: (np.round(np.array(v, dtype=float), 3).tolist()) for k, v in r.items()})
json.dump(res, open("analysis.json", "w"), indent=1)
