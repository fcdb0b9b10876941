"""(b) with another per-step budget from the table's stored Lorenz-63 starts (``maps/lorenz63-obs*/warm``)
on the table's truths (``benchmarks/amortised_ot.py``'s key 2026, 10 simulations, N = 1000) over
filter keys 0-2, paired truth by truth with the online OT filter's runs on the same keys
(``distilled/l63*/online.json``): (b) - 1.1 online per truth, averaged over the keys. Adds
``FIRST_FLOOR`` to ``warm_budget_table.json`` beside it.

    PYTHONPATH=.:benchmarks taskset -c 0 python benchmarks/results/amortised_ot/warm_budget_table.py 32,16
"""
import json
import os
import sys

import numpy as np
from amortised_warm_from import score
from ot_filter.amortised import load_map
from ot_filter.experiments._common import write_text_atomic
from ot_filter.experiments.amortised import warm_options
from ot_filter.updates.amortised import amortised_ot

HERE = os.path.dirname(os.path.abspath(__file__))
KEYS = (0, 1, 2)
CASES = {"x1x3": ((0, 2), "maps/lorenz63-obs0,2/warm", "distilled/l63/online.json"),
         "x1": ((0,), "maps/lorenz63-obs0/warm", "distilled/l63x1/online.json")}
schedule = tuple(int(v) for v in sys.argv[1].split(","))
path = os.path.join(HERE, "warm_budget_table.json")
for case, (observed, start, online_path) in CASES.items():
    warm = load_map(os.path.join(HERE, start))
    update = amortised_ot(warm, **dict(warm_options(warm, "lorenz63"), num_iterations=schedule))
    online = json.load(open(os.path.join(HERE, online_path)))
    runs = {k: score("lorenz63", 3, observed, "amortised_warm", update, k) for k in KEYS}
    method = np.mean([runs[k]["mse_per_simulation"] for k in KEYS], axis=0)
    reference = np.mean([online[str(k)]["mse_per_simulation"] for k in KEYS], axis=0)
    difference = method - 1.1 * reference
    entry = {"runs": runs, "mse": float(method.mean()), "online": float(reference.mean()),
             "over_online": float(method.mean() / reference.mean()), "minus_1.1_online": float(difference.mean()),
             "stderr": float(difference.std(ddof=1) / np.sqrt(difference.size))}
    print(case, schedule, {k: v for k, v in entry.items() if k != "runs"}, flush=True)
    record = json.load(open(path)) if os.path.exists(path) else {}
    record.setdefault(case, {})[f"{schedule[0]}_{schedule[1]}"] = entry
    write_text_atomic(path, json.dumps(record, indent=1))
