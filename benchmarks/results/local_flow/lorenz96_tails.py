"""Why the extreme starts are translated: the localised flow on Lorenz-96 with y = x^2 (noise std
10, every 4 RK4 steps, N = 100, the catalogue's windows and deterministic layer, 400 iterations
halving to 50), one truth, 40 steps, with NO translation (tail_particles=0) and the far-thrown
test off, beside the LETKF applied to the same forecast. Per step: how far (standardised by the
prior) the worst particle lies beyond the test's reach max(6, |prior| + 2), how many do, and that
particle's prior, flow and LETKF values.

    PYTHONPATH=.:benchmarks python benchmarks/results/local_flow/lorenz96_tails.py

Output: lorenz96_tails.log (steps 18-39 as printed during development by an earlier form of
this script, the same settings; the particle index, prior, flow and LETKF values in prior
standard deviations).
"""
import jax
import jax.numpy as jnp
import numpy as np

import ot_lorenz96 as bench
import ot_filter as otf
from ot_filter.experiments._common import simulate_truths
from ot_filter.models import lorenz96
from ot_filter.localisation import taper_support
from ot_filter.runner.catalogue import LORENZ96_LOCAL, cell_key
from ot_filter.transport import divergence

divergence.MAX_TRANSPORT_DISTANCE = 1e9  # the far-thrown test off: watch the particles instead
model = lorenz96(dim=40, observation_operator="square", observation_noise_std=10.0, steps_per_observation=4)
truth_key, _ = jax.random.split(cell_key(0, 40, 0))
states, observations = simulate_truths(truth_key, model, 40, 1)
windows = otf.local_windows(model.geometry, taper_support(LORENZ96_LOCAL["ot_taper_radius"], "gaspari_cohn"), 0.0)
update = otf.local_flow(windows, num_iterations=(400, 50), enkf_layer="deterministic", taper="gaspari_cohn",
                        inflation=LORENZ96_LOCAL["inflation"], fresh_observations=False, tail_particles=0)
letkf = bench.build("letkf", model)
key = jax.random.key(3)
particles = jax.vmap(model.sample_initial)(jax.random.split(key, 100))
state = update.init(key, particles, model)
letkf_state = letkf.init(jax.random.key(0), jnp.zeros((100, 40)), model)
propagate = jax.jit(lambda k, x: jax.vmap(model.sample_transition)(jax.random.split(k, 100), x))
for step in range(40):
    key, forecast_key, update_key = jax.random.split(key, 3)
    particles = propagate(forecast_key, particles)
    posterior, state, info = update.apply(update_key, state, particles, observations[0, step], model)
    analysis, _, _ = letkf.apply(update_key, letkf_state, particles, observations[0, step], model)
    scaling = state.standardisation
    prior_z, flow_z, letkf_z = (np.asarray(scaling.standardise_x(x)) for x in (particles, posterior, analysis))
    beyond = np.abs(flow_z) - np.maximum(6, np.abs(prior_z) + 2)
    worst = np.unravel_index(np.argmax(beyond), beyond.shape)
    print(step, "beyond", beyond.max().round(2), "count", int((beyond > 0).sum()), "particle", worst,
          "prior", prior_z[worst].round(2), "flow", flow_z[worst].round(2), "letkf", letkf_z[worst].round(2),
          flush=True)
    particles = posterior
