"""Where the global map's error lies (n = 10, static example, the runs of mixture_run.py): the mass
on each side of 0 per coordinate (exact: 1/2) and W1 of |x| per coordinate to the exact |x|
(the shape within the modes, blind to which mode a particle is in), beside N exact samples.

    cd benchmarks/results/averaged_maps/global_diagnostics
    PYTHONPATH=../../../..:../../.. python decompose.py > decompose.txt   (needs seed0.npz, seed1.npz)
"""
import numpy as np, jax
from ot_sample_size import exact_scoring
w1, exact = exact_scoring(10)
reference = np.asarray(exact(jax.random.key(5), 200_000))


def folded_w1(x):
    a = np.sort(np.abs(x), 0)
    b = np.quantile(np.abs(reference), (np.arange(len(a)) + 0.5) / len(a), axis=0)
    return np.mean(np.abs(a - b), 0)


for seed in (0, 1):
    d = np.load(f"seed{seed}.npz")
    own, prior = d["own"], d["prior"]
    floor = np.asarray(exact(jax.random.key(11 + seed), 1000))
    print(f"prior sample {seed}: N exact samples: W1 {np.asarray(w1(floor)).mean():.3f}, |x| W1 {folded_w1(floor).mean():.3f}, "
          f"|share - 1/2| {np.abs((floor > 0).mean(0) - 0.5).mean():.3f}; the prior's own |share - 1/2| "
          f"{np.abs((prior > 0).mean(0) - 0.5).mean():.3f}")
    for k in range(own.shape[0]):
        x = own[k, -1]
        print(f"  training {k}: W1 {np.asarray(w1(x)).mean():.3f}, |x| W1 {folded_w1(x).mean():.3f}, "
              f"|share - 1/2| {np.abs((x > 0).mean(0) - 0.5).mean():.3f}, sd of |x| {np.abs(x).std(0).mean():.3f} "
              f"(exact {np.abs(reference).std(0).mean():.3f}), mean |x| {np.abs(x).mean():.3f} (exact {np.abs(reference).mean():.3f})")
