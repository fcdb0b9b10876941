"""Variants of local_flow in the dynamic example (n = 10, the first 4 of the 10 truths of
ot_dimension.py's dynamic part, 20 steps), run when the default budget was (2000, 100):

    PYTHONPATH=. python dynamic_variants.py 10 4 default,floor500,tail0,lr3e-4_warm,nofresh

Output: dynamic_variants_n10_4sims.log (name, mean W1 per coordinate, worst coordinate, per simulation)."""
import sys

import jax

import ot_filter as otf
from ot_filter.experiments.dynamic_example import dynamic_model, run_dynamic_example

dim, simulations = int(sys.argv[1]), int(sys.argv[2])
windows = otf.local_windows(dynamic_model(dim).geometry, 0.0)
variants = {
 "default": otf.local_flow(windows, num_iterations=(2000, 100)),
 "floor500": otf.local_flow(windows, num_iterations=(2000, 500)),
 "tail0": otf.local_flow(windows, num_iterations=(2000, 100), tail_particles=0),
 "lr3e-4_warm": otf.local_flow(windows, num_iterations=(2000, 100), learning_rate=3e-4),
 "nofresh": otf.local_flow(windows, num_iterations=(2000, 100), fresh_observations=False),
}
chosen = sys.argv[3].split(",")
result = run_dynamic_example(jax.random.key(2026), dim=dim, num_particles=1000, num_steps=20,
                             num_simulations=simulations, methods=(), bandwidth=4.0, standardise=True,
                             average_from=1.0, keep=0, extra_updates={name: variants[name] for name in chosen})
for name in chosen:
    exact = result["metrics"][name]["exact"]
    print(name, round(exact["w1"]["mean"], 4), round(exact["w1_max"]["mean"], 4),
          [round(value, 3) for value in exact.get("w1_per_simulation", [])], flush=True)
print("floor", result["metrics"]["floor"]["w1"]["mean"])
