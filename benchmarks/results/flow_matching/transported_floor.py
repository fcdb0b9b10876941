"""Record of 2026-12-07: the floor of a transport of the static example's own prior particles.

    PYTHONPATH=. python benchmarks/results/flow_matching/transported_floor.py [PRIOR_KEY]

Every map-based update moves the N prior particles it is given, so its W1 to the exact posterior
carries those particles' own sampling error. The exact transport of them (each coordinate by the
monotone map F_post^-1(Phi(x)), the 1-D optimal transport from N(0, 1) to the exact posterior,
which is what the coordinates' independence makes exact) scores that error alone. Printed beside
the N-sample floor (N fresh exact samples) on the same two prior samples and dimensions as
``benchmarks/flow_matching_static.py``.
"""
import json, sys
import jax, jax.numpy as jnp, numpy as np
from jax.scipy.stats import norm
from ot_filter import metrics
from ot_filter.models import squared_observation
from ot_filter.reference import squared_observation_posterior

N, NOISE = 1000, 0.4
prior_key = int(sys.argv[1]) if len(sys.argv) > 1 else 2026
exact = squared_observation_posterior(1.0, NOISE, scale=0.5)
grid = np.asarray(exact.grid, np.float64)
density = np.asarray(exact.density, np.float64)
cdf = np.cumsum(density); cdf /= cdf[-1]
for dim in (2, 10, 20, 50):
    model = squared_observation(dim=dim, noise=NOISE, observation_scale=0.5, static=True)
    masses = jnp.broadcast_to(jnp.asarray(exact.density), (dim,) + exact.density.shape)
    rows = []
    for seed in jax.random.split(jax.random.key(prior_key), 2):
        prior_key_, _, _, floor_key, compare_key = jax.random.split(seed, 5)
        prior = jax.vmap(model.sample_initial)(jax.random.split(prior_key_, N))
        u = np.asarray(norm.cdf(np.asarray(prior, np.float64)))
        moved = np.interp(u, cdf, grid)
        w1 = metrics.compare_to_product_grid(compare_key, jnp.asarray(moved, jnp.float32), None, jnp.asarray(exact.grid), masses, N).w1
        floor = metrics.compare_to_product_grid(compare_key, metrics.product_grid_sample(floor_key, jnp.asarray(exact.grid), masses, N), None, jnp.asarray(exact.grid), masses, N).w1
        rows.append((float(w1.mean()), float(floor.mean()), float(w1.max())))
    print(json.dumps({"prior_key": prior_key, "dim": dim, "transported_floor": sum(r[0] for r in rows) / 2,
                      "n_sample_floor": sum(r[1] for r in rows) / 2, "transported_worst": max(r[2] for r in rows)}))
