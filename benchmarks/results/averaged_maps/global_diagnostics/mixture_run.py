"""Diagnostic: the global ot() defaults at n = 10 (static example, benchmarks/ot_sample_size.py's prior
samples), trained K times on one prior sample in chunks of 500 iterations (benchmarks/ot_training_curve.py's
build); the transported ensembles (own particles and 10,000 fresh ones) saved at the checkpoints from 5,000
iterations on. analyse.py scores averages and mixtures of them.

    PYTHONPATH=.:benchmarks python mixture_run.py SEED 3 seedSEED.npz
"""
import sys, time
import jax, jax.numpy as jnp, numpy as np
sys.path[:0] = [".", "benchmarks"]
from ot_training_curve import build
seed, keys, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]  # out: seed0.npz / seed1.npz (not kept)
chunk, chunks, save_from = 500, 20, 10
setup, step, score = build(dim=10, num_train=1000, num_evaluate=10_000, options={}, chunk=chunk)
apply_key0, state0, prior, fresh, simulated, floors = setup(jax.random.split(jax.random.key(2026), 2)[seed])
# the training keys: k = 0 is ot_training_curve's; others fold k into the init and apply keys
own_all, fresh_all, div_all = [], [], []
y = jnp.full((10,), 1.0)
import ot_filter as otf
from ot_filter.models import squared_observation
model = squared_observation(dim=10, noise=0.4, observation_scale=0.5, static=True)
update = otf.ot(num_iterations=chunk)
transport = jax.jit(lambda s, x: update.transport(s, x, y))
transport_fresh = jax.jit(lambda s, x, sim: update.transport(s, x, y, sim))
for k in range(keys):
    if k == 0:
        state, apply_key = state0, apply_key0
    else:
        state = jax.jit(lambda key: update.init(key, prior, model))(jax.random.fold_in(jax.random.key(7), 1000 * seed + k))
        apply_key = jax.random.fold_in(apply_key0, k)
    owns, freshs, divs = [], [], []
    t = time.perf_counter()
    for c in range(chunks):
        state, o = step(jax.random.fold_in(apply_key, c), state, prior, fresh, simulated)
        if c + 1 >= save_from:
            owns.append(np.asarray(transport(state, prior)))
            freshs.append(np.asarray(transport_fresh(state, fresh, simulated)))
            divs.append(bool(o["diverged"]))
    print(seed, k, round(time.perf_counter() - t), "s", float(np.mean(o["in_sample"])), divs, flush=True)
    own_all.append(owns); fresh_all.append(freshs); div_all.append(divs)
np.savez_compressed(out, own=np.array(own_all), fresh=np.array(fresh_all), diverged=np.array(div_all),
                    prior=np.asarray(prior), floor_in=float(np.mean(floors["floor_in_sample"])),
                    floor_out=float(np.mean(floors["floor_out_of_sample"])))
print("saved", out, flush=True)
