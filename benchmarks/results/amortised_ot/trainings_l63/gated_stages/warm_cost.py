"""Run time of (b) at several per-step budgets, from the stage's width-64 start and from that
start distilled to width 32 (``warm_w32``), against the online OT filter, (a) and the EnKF:
whole 500-step Lorenz-63 runs (the online filter's 1,024-iteration start included), N = 1000,
vmapped over the simulations, every filter timed in turn in one process
(``amortised_cost.measure``: the best of ``rounds``); writes ``warm_cost.json`` beside it.

    PYTHONPATH=.:benchmarks taskset -c 0 python benchmarks/results/amortised_ot/trainings_l63/gated_stages/warm_cost.py
"""
import json
import os

from amortised_cost import measure
from ot_filter.amortised import load_map
from ot_filter.experiments._common import write_text_atomic
from ot_filter.experiments.amortised import experiment_model, online_update, warm_options
from ot_filter.updates.amortised import amortised_ot
from ot_filter.updates.enkf import enkf

HERE = os.path.dirname(os.path.abspath(__file__))
STAGE, OBSERVED = "x1x3_key71", (0, 2)
SIMULATIONS, STEPS, ROUNDS = 2, 500, 2

maps = os.path.join(HERE, f"{STAGE}_maps")
kept = load_map(maps)
updates = {"EnKF": enkf(), "online OT filter": online_update("lorenz63"), "(a)": amortised_ot(kept)}
for start in ("warm", "warm_w32"):
    warm = load_map(os.path.join(maps, start))
    for schedule in ((32, 8), (32, 16), (32, 32)):
        options = dict(warm_options(warm, "lorenz63"), num_iterations=schedule)
        updates[f"(b) width {warm.config.width}, {schedule}"] = amortised_ot(warm, **options)
seconds = measure(experiment_model("lorenz63", 3, OBSERVED), updates, STEPS, SIMULATIONS, 1000, ROUNDS)
online = seconds["online OT filter"]
record = {"stage": STAGE, "simulations": SIMULATIONS, "steps": STEPS, "rounds": ROUNDS, "particles": 1000,
          "ms_per_step": {k: v * 1e3 for k, v in seconds.items()},
          "over_online": {k: v / online for k, v in seconds.items()}}
for label, value in seconds.items():
    print(f"{label}: {value * 1e3:.2f} ms a step and simulation, {value / online:.2f} of the online filter", flush=True)
write_text_atomic(os.path.join(HERE, "warm_cost.json"), json.dumps(record, indent=1))
