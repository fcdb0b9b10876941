"""The deterministic layer on a linear-Gaussian case: the layer (the LETKF of the windows) is then
the exact local posterior, and a flow or map from it should not move it. Lorenz-96 geometry,
12 coordinates, N = 100, radius 2 (step taper), three prior seeds; mean and mean absolute
(flow - LETKF) / LETKF's posterior spread per coordinate.

    PYTHONPATH=. python benchmarks/results/local_flow/layer_gaussian_check.py

Output: layer_gaussian_check.log (run before 0.2.22's default of fresh observations existed:
"flow" is fresh_observations=False, "flow_fresh" True, now the default for this model).
"""
import jax
import jax.numpy as jnp
import numpy as np

import ot_filter as otf
from ot_filter.localisation import local_windows

model = otf.models.lorenz96(dim=12)
letkf = otf.letkf(otf.localisation(model.geometry, 2.0, taper="step"))
for seed in range(3):
    prior = 3.0 + jax.random.normal(jax.random.PRNGKey(seed), (100, 12)) @ (0.3 * jnp.eye(12) + 0.1)
    observation = jax.vmap(model.observation_function)(prior[:1])[0] + 0.7
    windows = local_windows(model.geometry, 2.0)
    expected, _, _ = letkf.apply(jax.random.PRNGKey(3), letkf.init(jax.random.PRNGKey(3), prior, model), prior,
                                 observation, model)
    spread = np.asarray(expected).std(axis=0)
    updates = {"flow": otf.local_flow(windows, enkf_layer="deterministic", fresh_observations=False),
               "flow_fresh": otf.local_flow(windows, enkf_layer="deterministic", fresh_observations=True),
               "local_ot": otf.local_ot(windows, enkf_layer="deterministic")}
    for name, update in updates.items():
        posterior, _, info = update.apply(jax.random.PRNGKey(2), update.init(jax.random.PRNGKey(1), prior, model),
                                          prior, observation, model)
        difference = np.asarray(posterior - expected) / spread
        print(seed, name, bool(info.diverged), "mean|d|", np.abs(difference).mean().round(3),
              "mean d", difference.mean().round(3), flush=True)
