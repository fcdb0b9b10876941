"""W1 to the exact filter at each of the dynamic example's 20 steps (mean over 10 simulations),
with the positive mode's mass's mean distance from 1/2, for the methods given, and each
simulation's time average.

    PYTHONPATH=. python benchmarks/results/ot_dimension_etpf/local_ot_etpf/over_time.py DIM POWER METHODS

POWER replaces ``experiments._common.ETPF_POWER`` (the LETPF's share of the likelihood in
``local_ot_etpf`` and ``letkf_etpf``); METHODS is a comma-separated list of the experiment's
methods. The truths are ``ot_dimension.py``'s (key 2026, N = 1000). A method's training keys
depend on its place in the list (the experiment folds the index in), so a method's figure can
differ between lists.
"""
import sys

import jax
import numpy as np

import ot_filter.experiments._common as common
from ot_filter.experiments.dynamic_example import run_dynamic_example

dim, power, methods = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3].split(",")
common.ETPF_POWER = power
result = run_dynamic_example(jax.random.key(2026), dim=dim, num_particles=1000, num_steps=20, num_simulations=10,
                             methods=methods, bandwidth=4.0)
for name in methods:
    summary = result["metrics"][name]
    w1 = result["arrays"][f"{name}_w1"]  # [simulations, steps], mean over coordinates
    print(name, "power", power, "W1", summary["exact"]["w1"]["mean"], "diverged", summary.get("diverged_steps"),
          "imbalance", round(summary["mode_imbalance"], 3))
    print("  W1 over time, mean over simulations", np.round(w1.mean(axis=0), 3).tolist())
    print("  W1 over time, median over simulations", np.round(np.median(w1, axis=0), 3).tolist())
    print("  W1 per simulation, mean over time", np.round(w1.mean(axis=1), 3).tolist())
