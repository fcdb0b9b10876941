"""Trainings 3 and 4 of mixture_run.py's scheme (keys folded the same way), final ensembles only;
then averages of 3, 4 and 5 trainings with the saved 0-2.

    PYTHONPATH=.:benchmarks python more_keys.py SEED
"""
import sys, time, json
import jax, jax.numpy as jnp, numpy as np
sys.path[:0] = [".", "benchmarks"]
from ot_training_curve import build
from ot_sample_size import exact_scoring
import ot_filter as otf
from ot_filter.models import squared_observation
seed = int(sys.argv[1])
chunk, chunks = 500, 20
setup, step, score = build(dim=10, num_train=1000, num_evaluate=10_000, options={}, chunk=chunk)
apply_key0, state0, prior, fresh, simulated, floors = setup(jax.random.split(jax.random.key(2026), 2)[seed])
model = squared_observation(dim=10, noise=0.4, observation_scale=0.5, static=True)
update = otf.ot(num_iterations=chunk)
y = jnp.full((10,), 1.0)
transport = jax.jit(lambda s, x: update.transport(s, x, y))
finals = []
for k in (3, 4):
    state = jax.jit(lambda key: update.init(key, prior, model))(jax.random.fold_in(jax.random.key(7), 1000 * seed + k))
    apply_key = jax.random.fold_in(apply_key0, k)
    t = time.perf_counter()
    for c in range(chunks):
        state, o = step(jax.random.fold_in(apply_key, c), state, prior, fresh, simulated)
    finals.append(np.asarray(transport(state, prior)))
    print(seed, k, round(time.perf_counter() - t), "s", float(np.mean(o["in_sample"])), bool(o["diverged"]), flush=True)
d = np.load(f"seed{seed}.npz")  # mixture_run.py's (not kept)
own = np.concatenate([d["own"][:, -1], np.stack(finals)])  # [5, N, n]
w1, _ = exact_scoring(10)
floor = float(d["floor_in"])
res = {"seed": seed, "floor": floor, "single": [float(np.mean(w1(jnp.asarray(x)))) for x in own]}
for K in (3, 4, 5):
    res[f"average{K}"] = float(np.mean(w1(jnp.asarray(own[:K].mean(0)))))
    res[f"average{K}_worst"] = float(np.max(w1(jnp.asarray(own[:K].mean(0)))))
res["average3_of_keys_2to4"] = float(np.mean(w1(jnp.asarray(own[2:5].mean(0)))))
print(json.dumps(res), flush=True)
json.dump(res, open(f"more_keys_{seed}.json", "w"), indent=1)  # both seeds: more_trainings.json
