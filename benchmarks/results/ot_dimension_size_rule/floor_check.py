"""Record of 2026-12-07: the static example's N-sample floor, computed independently of the library.

    python benchmarks/results/ot_dimension_size_rule/floor_check.py

One coordinate's exact posterior of the chapter's static example (x ~ N(0, 1), y = x^2 / 2 +
0.4 w, y = 1) on a fine grid; the expected W1 between N = 1000 exact samples and that posterior
(the floor the tables use), and between two independent sets of N exact samples, each averaged
over 200 draws. numpy only: a check of ``metrics.compare_to_product_grid`` and
``metrics.product_grid_sample``, whose floor at n = 10 is 0.0403 on the tables' two prior samples.
"""
import json

import numpy as np

grid = np.linspace(-5.0, 5.0, 200_001)
density = np.exp(-grid**2 / 2 - (1.0 - grid**2 / 2) ** 2 / (2 * 0.4**2))
cdf = np.cumsum(density / density.sum())
rng = np.random.default_rng(0)


def draw(num):
    return np.sort(np.interp(rng.random(num), cdf, grid))


def w1_to_exact(sample):
    empirical = np.searchsorted(sample, grid, side="right") / len(sample)
    return float(np.sum(np.abs(empirical - cdf)) * (grid[1] - grid[0]))


num, repeats = 1000, 200
to_exact = [w1_to_exact(draw(num)) for _ in range(repeats)]
between = [float(np.mean(np.abs(draw(num) - draw(num)))) for _ in range(repeats)]
record = {"N": num, "repeats": repeats,
          "w1_sample_to_exact": {"mean": np.mean(to_exact), "stderr": np.std(to_exact) / np.sqrt(repeats)},
          "w1_between_two_samples": {"mean": np.mean(between), "stderr": np.std(between) / np.sqrt(repeats)}}
print(json.dumps(record, indent=1))
