"""Which divergence test the localised OT filter's fallbacks come from, per truth (Lorenz-96,
squared observations): PYTHONPATH=.:benchmarks python fallback_diagnosis.py NOISE EVERY N SIMULATIONS METHOD
(the record beside it: 3 8 400 4 local_ot:64::512)."""
import os, sys
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import jax, numpy as np
import ot_filter as otf
from ot_filter.experiments._common import simulate_truths
from ot_filter.models import lorenz96
from ot_filter.runner.catalogue import cell_key
from ot_filter.transport.divergence import MAX_PREDICTIVE_Z
noise, every, N, sims, method = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
import ot_lorenz96 as b
model = lorenz96(dim=40, observation_operator="square", observation_noise_std=noise, steps_per_observation=every)
truth_key, filter_key = jax.random.split(cell_key(0, 40, 0))
states, obs = simulate_truths(truth_key, model, 500, sims)
keys = jax.random.split(filter_key, sims)
upd = b.build(method, model)
@jax.jit
def go(keys, obs):
    def one(k, y):
        r = otf.run_filter(k, model, upd, y, N, save_every=0)
        return r.mean, r.info
    return jax.vmap(one)(keys, obs)
means, info = go(keys, obs)
err = np.sqrt(((np.asarray(means) - np.asarray(states))**2).mean(-1))  # [sims, T]
out = {}
for s in range(sims):
    d = dict(rmse_late=float(err[s, 250:].mean()))
    if hasattr(info, "diverged"):
        dv = np.asarray(info.diverged[s]); z = np.asarray(info.predictive_z[s]); L = np.asarray(info.final_loss[s]); tr = np.asarray(info.innovation_trend[s])
        d.update(fallbacks=int(dv.sum()), z_fail=int((~(z <= MAX_PREDICTIVE_Z)).sum()), z_fail_and_div=int((dv & ~(z <= MAX_PREDICTIVE_Z)).sum()),
                 loss_max=float(np.nanmax(np.abs(L[np.isfinite(L)]))) if np.isfinite(L).any() else None,
                 trend_q=[float(q) for q in np.quantile(tr, [0.05, 0.5, 0.95])],
                 first_fallback=int(np.argmax(dv)) if dv.any() else -1)
    d["err_t"] = [round(float(e), 3) for e in err[s, ::25]]
    out[s] = d
    print(s, {k: v for k, v in d.items()}, flush=True)
