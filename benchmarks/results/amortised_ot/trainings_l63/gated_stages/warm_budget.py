"""(b) with another per-step budget from each gated stage's start, on its 30 fresh truths (key
2027), paired with the online filter's run there; adds ``amortised_warm_FIRST_FLOOR`` to each
stage's record (``amortised_WARM_FIRST_FLOOR`` for a start stored under ``{stage}_maps/WARM``, e.g.
``warm_w32``, each stage's start distilled to width 32 (bank 21-27 s, distillation 62-68 s), made by

    PYTHONPATH=.:benchmarks python benchmarks/amortised_distil.py --experiment lorenz63 --observed 0,2 \
        --map benchmarks/results/amortised_ot/trainings_l63/gated_stages/x1x3_key71_maps/warm \
        --widths 32 --skip score,cost --key 38 --out /tmp/distil_x1x3_key71
    (the same with --observed 0 and x1_key72), then /tmp/distil_STAGE/maps/width32 moved to
    STAGE_maps/warm_w32 with the run's distil.json).

    PYTHONPATH=. python benchmarks/results/amortised_ot/trainings_l63/gated_stages/warm_budget.py 32,32
    PYTHONPATH=. python benchmarks/results/amortised_ot/trainings_l63/gated_stages/warm_budget.py 32,8 warm_w32 x1_key72
"""
import json
import os
import sys

import jax
import numpy as np
from ot_filter.amortised import load_map
from ot_filter.amortised.selection import score_filter
from ot_filter.experiments.amortised import experiment_model, selection_truths, warm_options
from ot_filter.updates.amortised import amortised_ot
from ot_filter.experiments._common import write_text_atomic

HERE = os.path.dirname(os.path.abspath(__file__))
schedule = tuple(int(v) for v in sys.argv[1].split(","))
warm_name = sys.argv[2] if len(sys.argv) > 2 else "warm"
STAGES = {"x1x3_key71": (0, 2), "x1_key72": (0,)}
for name in sys.argv[3].split(",") if len(sys.argv) > 3 else STAGES:
    observed = STAGES[name]
    record_path = os.path.join(HERE, f"{name}.json")
    fresh = json.load(open(record_path))["fresh_truths"]["2027"]
    warm = load_map(os.path.join(HERE, f"{name}_maps", warm_name))
    options = dict(warm_options(warm, "lorenz63"), num_iterations=schedule)
    model = experiment_model("lorenz63", 3, observed)
    truth_model, skip = selection_truths("lorenz63", 3, observed)
    score = score_filter(jax.random.key(2027), model, amortised_ot(warm, **options), num_simulations=30, num_steps=500,
                         num_particles=1000, skip_steps=skip, truth_model=truth_model).record()
    label = f"amortised_{warm_name}_{schedule[0]}_{schedule[1]}"
    reference = np.asarray(fresh["ot"]["per_simulation"], float)
    difference = np.asarray(score["per_simulation"], float) - 1.1 * reference
    paired = {"over_online": score["mse"] / fresh["ot"]["mse"], "minus_1.1_online": float(difference.mean()),
              "stderr": float(difference.std(ddof=1) / np.sqrt(difference.size))}
    print(name, label, score["mse"], score["fallback_steps"], round(score["seconds"]), paired, flush=True)
    record = json.load(open(record_path))  # read again: another budget's run may have written it meanwhile
    record["fresh_truths"]["2027"].update({label: score, label + "_paired": paired})
    write_text_atomic(record_path, json.dumps(record, indent=1))
