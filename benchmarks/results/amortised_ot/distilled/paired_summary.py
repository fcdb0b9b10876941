"""Paired summary of the distilled maps: run from this folder (python paired_summary.py)."""
import json, numpy as np
def pairs(distil, online, metric, labels, keys=(0,1,2), factor=1.25):
    r = json.load(open(distil))["scores"]; o = json.load(open(online)) if isinstance(online, str) else online
    out = {}
    for lab in labels:
        a = np.concatenate([r[f"{lab}_{k}"][metric] for k in keys]); b = np.concatenate([o[str(k)][metric] for k in keys])
        t = np.concatenate([r[f"teacher_{k}"][metric] for k in keys]); d = a - factor * b; n = len(d)
        out[lab] = dict(mean=float(a.mean()), se=float(a.std(ddof=1)/np.sqrt(n)), online=float(b.mean()), ratio=float(a.mean() / b.mean()),
                        minus_target=float(d.mean()), minus_target_se=float(d.std(ddof=1) / np.sqrt(n)),
                        minus_teacher=float((a-t).mean()), minus_teacher_se=float((a-t).std(ddof=1)/np.sqrt(n)),
                        ratio_per_key=[round(float(np.mean(r[f"{lab}_{k}"][metric]) / np.mean(o[str(k)][metric])), 3) for k in keys],
                        fallback_steps=[r[f"{lab}_{k}"].get("diverged_steps") for k in keys])
        print(lab, {k: (round(v, 4) if isinstance(v, float) else v) for k, v in out[lab].items()})
    return out
res = {}
o = json.load(open("n2/online.json"))
for tag, path in [("lr1e-3", "n2/distil_rate1e-3.json"), ("lr3e-3", "n2/distil.json")]:
    print("dynamic n=2 W1", tag); res[f"dynamic_n2_{tag}"] = pairs(path, o, "w1_per_simulation", ["teacher", "width16", "width24"])
for tag, path in [("lr1e-3", "l63/distil_rate1e-3.json"), ("lr3e-3", "l63/distil.json")]:
    print("L63 1,3 MSE", tag); res[f"lorenz63_obs0,2_{tag}"] = pairs(path, "l63/online.json", "mse_per_simulation", ["teacher", "width16", "width24"])
for tag, path, labs in [("lr1e-3", "l63x1/distil_rate1e-3.json", ["teacher", "width16", "width32"]), ("lr3e-3", "l63x1/distil.json", ["teacher", "width16", "width24"])]:
    print("L63 1 MSE", tag); res[f"lorenz63_obs0_{tag}"] = pairs(path, "l63x1/online.json", "mse_per_simulation", labs)
json.dump(res, open("paired_summary.json", "w"), indent=1)
