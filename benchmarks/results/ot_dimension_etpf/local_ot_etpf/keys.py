"""The static localised update's spread over training keys: the same 2 prior samples (the README
table's), local_ot at method index 0..5 (the static example folds the method's index into its
training key)."""
import sys
import json
import jax
from ot_filter.experiments.static_example import run_static_example
cheap = ["enkf", "letkf", "sir", "local_etpf", "letkf_etpf"]
dim = int(sys.argv[1])
out = []
for index in range(6):
    methods = cheap[:index] + ["local_ot"]
    r = run_static_example(jax.random.key(2026), noise=0.4, num_particles=1000, num_seeds=2, dim=dim, methods=methods)
    m = r["metrics"]
    out.append(dict(index=index, w1=m["local_ot"]["w1"], w1_max=m["local_ot"]["w1_max"], floor=m["floor_w1"]))
    print(index, "local_ot W1 %.4f (lower seed %s) floor %.4f" % (m["local_ot"]["w1"]["mean"], m["local_ot"]["w1"]["min"], m["floor_w1"]["mean"]), m["local_ot"]["w1"], flush=True)
json.dump(out, open(f"/tmp/keys_static_{dim}.json", "w"), default=str)
