"""The benchmark suite in one command: runs the benchmark scripts one after the other (never
concurrently: they time things) and writes an index of their tables.

    PYTHONPATH=. python benchmarks/suite.py [--quick] [--dapper-python PATH] [--cuthbert-python PATH]

- lorenz_twin.py: classic filters on Lorenz-63 / Lorenz-96 twin experiments against DAPPER
  (``--dapper-python``: an interpreter with DAPPER) and cuthbert (``--cuthbert-python``), same
  truths and machine, one run: seconds after compilation, compile seconds, rmse.a, ratios;
- scaling.py: time and memory vs N (10^2 .. 10^6) and n (Lorenz-96, 40 .. 1000), fitted
  exponents; the OT update's iterations per second vs mini-batch, width, n and N;
- continuous_time.py --parts speed: seconds per FPF step of each gain at N = 10^3, 10^4;
- progress_overhead.py: the cost of in-scan progress reports.

On a GPU the same command measures the GPU (JAX's default backend); every table names its device.
Writes benchmarks/results/suite.{json,md}: per script the command, exit code and seconds, and
the Markdown tables the scripts wrote.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parent
RESULTS = BENCHMARKS / "results"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="each script's smoke settings")
    parser.add_argument("--dapper-python")
    parser.add_argument("--cuthbert-python")
    args = parser.parse_args()
    quick = ["--quick"] if args.quick else []
    twin = [*quick]
    if args.dapper_python:
        twin += ["--dapper-python", args.dapper_python]
    if args.cuthbert_python:
        twin += ["--cuthbert-python", args.cuthbert_python]
    scripts = [
        ("lorenz_twin.py", twin, ["lorenz_twin.md"]),
        ("scaling.py", quick, ["scaling.md"]),
        ("continuous_time.py", ["--parts", "speed", *quick], ["continuous_time/results.md"]),
        ("progress_overhead.py", ["--repeats", "3"] if args.quick else [], ["progress_overhead.md"]),
    ]
    env = dict(os.environ, PYTHONPATH=str(BENCHMARKS.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    runs, sections = [], ["# Benchmark suite (benchmarks/suite.py)", ""]
    for script, options, tables in scripts:
        command = [sys.executable, str(BENCHMARKS / script), *options]
        print("$", " ".join(command), flush=True)
        start = time.perf_counter()
        code = subprocess.run(command, env=env).returncode
        runs.append({"script": script, "command": command, "exit_code": code,
                     "seconds": time.perf_counter() - start})
        for table in tables:
            path = RESULTS / table
            if code == 0 and path.exists():
                sections += [path.read_text().replace("\n# ", "\n## ").replace("# ", "## ", 1), ""]
            else:
                sections += [f"## {script}: exit code {code}, no table", ""]
    (RESULTS / "suite.json").write_text(json.dumps({"quick": args.quick, "runs": runs}, indent=1) + "\n")
    (RESULTS / "suite.md").write_text("\n".join(sections))
    print(f"wrote {RESULTS / 'suite.md'}")
    sys.exit(max(run["exit_code"] for run in runs))


if __name__ == "__main__":
    main()
