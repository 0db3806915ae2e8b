"""Is float32 enough for tuning? The batch tuner's gradient at its start in float64 and in float32 (JSON on stdout).

A GPU moves half the bytes in float32, so a batch job would run faster with JAX's float64 off.
This evaluates what :mod:`benchmarks.bench_batch` times (``pusupu_jax.tune.batch.BatchProblem``: one 0.05 s
training window on the first 0.2 s of the arc and p2p paths, kinematic-error seed 0, the
default groups) at the start gains, once per precision, each in a fresh interpreter (JAX's
float64 switch is process-wide), and compares the objective's terms and its gradient:

    python benchmarks/bench_precision.py [--window 0.05] [--path 0.2]

``relative_error`` per field is ``|g32 - g64| / |g64|`` per member; ``sign_agrees`` whether the
two point the same way, which is what an optimiser's step needs first.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys

import numpy as np

# one precision's terms and gradient, as JSON; argv: dtype, window [s], path [s]
_EVALUATE = """
import json, sys
from pusupu_jax.runtime import setup_jax
setup_jax(x64=sys.argv[1] == "float64")
import jax, numpy as np
from pusupu_jax import ServoParams
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.plant.model import ModelOptions
from pusupu_jax.tune.batch import BatchProblem
from pusupu_jax.tune.config import TuneConfig
from pusupu_jax.tune.run import ScenarioSpec
cfg = TuneConfig(windows=1, window_s=float(sys.argv[2]), baselines=())
specs = [ScenarioSpec(f"{kind}/seed0", kind, ModelOptions(kin_error_seed=0), path_s=float(sys.argv[3]))
         for kind in ("arc", "p2p")]
problem = BatchProblem(cfg, specs, [[0], [1]], ServoParams.table1(), HybridGains())
zb = problem.shard(jax.tree.map(lambda *v: jax.numpy.stack(v), *[problem.space.z0()] * 2))
problem.prepare(zb, 0)
(_, aux), grad = problem.value_and_grad(zb)
terms = {k: np.asarray(v, dtype=float).ravel().tolist() for k, v in aux["terms"].items()}
print(json.dumps({"value": np.asarray(aux["value"], dtype=float).tolist(), "terms": terms,
                  "gradient": {k: np.asarray(v, dtype=float).reshape(2, -1).tolist() for k, v in grad.items()}}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=float, default=0.05, help="the training window [s]")
    ap.add_argument("--path", type=float, default=0.2, help="the first seconds of each path [s]")
    args = ap.parse_args()
    runs = {}
    for dtype in ("float64", "float32"):
        r = subprocess.run(
            [sys.executable, "-c", _EVALUATE, dtype, str(args.window), str(args.path)], capture_output=True, text=True
        )
        if r.returncode:
            sys.exit(f"bench_precision: the {dtype} evaluation failed: {r.stderr.strip().splitlines()[-1]}")
        runs[dtype] = json.loads(r.stdout)
    wide, narrow = runs["float64"], runs["float32"]
    fields = {}
    for name, g64 in wide["gradient"].items():
        g64, g32 = np.asarray(g64), np.asarray(narrow["gradient"][name])
        fields[name] = {
            "float64": g64.tolist(),
            "float32": g32.tolist(),
            "relative_error": (np.abs(g32 - g64) / np.abs(g64)).tolist(),
            "sign_agrees": (np.sign(g32) == np.sign(g64)).tolist(),
        }
    terms = {name: {"float64": t, "float32": narrow["terms"][name]} for name, t in wide["terms"].items()}
    signs = [s for f in fields.values() for row in f["sign_agrees"] for s in row]
    print(
        json.dumps(
            {
                "benchmark": "bench_precision",
                "host": platform.node(),
                "window_s": args.window,
                "path_s": args.path,
                "members": ["arc/seed0", "p2p/seed0"],
                "value": {"float64": wide["value"], "float32": narrow["value"]},
                "terms": terms,
                "gradient": fields,
                "signs_agreeing": f"{sum(signs)} of {len(signs)}",
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
