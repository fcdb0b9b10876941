"""What ot()'s size rule rests on: one global OT update of the static example for given sizes.

    PYTHONPATH=. python benchmarks/ot_sizes.py --dim 10 --options '{"width": 64, "batch_size": 1024}'

Static example (lambda_w = 0.4, y = 1, N = 1000), ``--seeds`` prior samples from key 2026, W1 per
coordinate to the exact posterior (mean over coordinates and the worst one) beside the floor of
N exact samples, and the wall seconds of the run (compilation and scoring included). Each run
appends one record to ``--out`` (JSON list); ``updates.ot.default_sizes`` cites these records.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax

from ot_filter.experiments._common import write_text_atomic
from ot_filter.experiments.static_example import run_static_example


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dim", type=int, required=True)
    parser.add_argument("--options", default="{}", help="ot() options as JSON (e.g. width, batch_size)")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/results/ot_dimension_size_rule/sizes.json")
    args = parser.parse_args()
    options = json.loads(args.options)
    start = time.perf_counter()
    result = run_static_example(jax.random.key(2026), noise=0.4, num_particles=1000, num_seeds=args.seeds,
                                dim=args.dim, methods=("ot",), ot_options=options)
    summary = result["metrics"]
    record = {"dim": args.dim, "options": options, "seeds": args.seeds,
              "w1": summary["ot"]["w1"]["mean"], "w1_worst_coordinate": summary["ot"]["w1_max"]["mean"],
              "floor_w1": summary["floor_w1"]["mean"], "seconds": round(time.perf_counter() - start, 1),
              "device": str(jax.devices()[0])}
    print(json.dumps(record), flush=True)
    records = json.load(open(args.out)) if os.path.exists(args.out) else []
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    write_text_atomic(args.out, json.dumps(records + [record], indent=1))


if __name__ == "__main__":
    main()
