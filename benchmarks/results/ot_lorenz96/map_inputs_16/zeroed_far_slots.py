"""Screen: localised OT on L96 squared obs with the map reading only the nearest k observation slots."""
import os, sys, json
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path[:0] = [".", "benchmarks"]
import jax, jax.numpy as jnp, numpy as np
import importlib
from ot_filter import metrics
from ot_filter.transport import networks as N
from ot_filter.experiments._common import simulate_truths
from ot_filter.models import lorenz96
from ot_filter.runner.catalogue import cell_key, lorenz96_local_ot
import ot_lorenz96 as B

K_KEEP = int(sys.argv[1])          # observation slots the networks read (0: all)
SIMS = int(sys.argv[2]); METHOD = sys.argv[3]; OUT = sys.argv[4]
ITER = int(sys.argv[5]) if len(sys.argv) > 5 else 64
REACH = 29

def column_mask(total):
    keep = np.ones(total, np.float32)
    if K_KEEP:
        keep[K_KEEP:REACH] = 0; keep[REACH + K_KEEP:2 * REACH] = 0
    return jnp.asarray(keep)

class P(N.PotentialNetwork):
    def __call__(self, x, y):
        return super().__call__(x, y * column_mask(y.shape[-1]))
class T(N.TransportNetwork):
    def __call__(self, x, y):
        return super().__call__(x, y * column_mask(y.shape[-1]))

def nets(structure):
    return P(structure.width, structure.num_blocks, structure.activation), T(structure.width, structure.num_blocks, structure.activation)
if METHOD == "local_ot":
    for name in ("ot_filter.updates.ot", "ot_filter.updates.local_ot"):
        importlib.import_module(name).networks = nets

import os as _os
OPERATOR = _os.environ.get("OPERATOR", "square")
model = lorenz96(dim=40, observation_operator=OPERATOR, observation_noise_std=10.0 if OPERATOR == "square" else 1.0, steps_per_observation=4 if OPERATOR == "square" else 1)
truth_key, filter_key = jax.random.split(cell_key(0, 40, 0))
states, observations = simulate_truths(truth_key, model, 500, SIMS)
keys = jax.random.split(filter_key, SIMS)
update = lorenz96_local_ot(model, ITER, warm_start=False) if METHOD == "local_ot" else METHOD
means, diverged, seconds = B.run(update, model, keys, observations, 100)
rmse = np.asarray(jax.vmap(metrics.rmse)(means, states))[:, 250:].mean(axis=1)
row = dict(k=K_KEEP, method=METHOD, iterations=ITER, rmse=rmse.tolist(), mean=float(rmse.mean()), fallbacks=int(diverged.sum()), seconds=seconds)
print(row, flush=True)
json.dump(row, open(OUT, "w"))
