"""The tuner's cold start: trace and compile time of its programs, with an empty compile cache (JSON on stdout).

``pusupu tune`` compiles its programs before its first iteration: the forward pass over the whole paths (which
renews the training windows' start states: the start at rest and one chunk of :func:`pusupu_jax.chunked.run_chunked`,
once per batch size of a group of paths) and the gradient over the windows.  Each is measured apart, as
``jit(...).lower()`` (the trace, to a jaxpr and then StableHLO) and ``.compile()`` (XLA), then the gradient is run
once.  Every measurement runs in a fresh interpreter with an empty persistent compile cache, so nothing is reused.

``--against DIR`` measures another source tree the same way (for example ``git archive main`` unpacked there),
alternating the two ``--repeat`` times, so that both see the same machine load::

    python benchmarks/bench_cold_start.py [--config default|quick] [--against DIR] [--xla-flags FLAGS] [--repeat 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

from timing import MOUNT_TREE  # beside this script

CHILD = (
    r"""
import time
t0 = time.perf_counter()
"""
    + MOUNT_TREE
    + r"""
import inspect
import json
import jax, jax.numpy as jnp
import numpy as np
from pusupu_jax.runtime import setup_jax
setup_jax(sys.argv[2])
from pusupu_jax import chunked, objectives
from pusupu_jax.cascade import control_mode
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import ServoParams
from pusupu_jax.tune.config import TuneConfig
from pusupu_jax.tune.run import Problem

cfg = TuneConfig.quick() if sys.argv[1] == "quick" else TuneConfig()
out = {"import_s": time.perf_counter() - t0}
t = time.perf_counter()
p = Problem(cfg, ServoParams.table1(), HybridGains())
out["problem_s"] = time.perf_counter() - t
z0 = p.space.z0()
servo, hybrid = p.space.apply(z0)
out["forward_trace_s"] = out["forward_compile_s"] = 0.0


def timed(lower):
    t = time.perf_counter()
    lowered = lower()
    out["forward_trace_s"] += time.perf_counter() - t
    t = time.perf_counter()
    compiled = lowered.compile()
    out["forward_compile_s"] += time.perf_counter() - t
    return compiled


if hasattr(p, "_whole"):  # a tree before the chunked forward pass: one program per path length
    for idx, models, refs in p.scenarios.groups.values():
        timed(lambda: p._whole.lower(servo, hybrid, models, refs))
else:
    # the start: one kept program, or (a tree with the plant's rest shared by the modes) the rest, then the controllers
    start_program = getattr(chunked, "_start_program", chunked._init_program)
    hybrid_arg = hybrid if control_mode(cfg.mode).hybrid else None
    # the programs as run_chunked calls them: a tree with ``_per_member`` gives every member its own gains (an axis
    # 0), an older one shares them (no axis); a tree whose programs take the axes as arguments gets them, and one
    # whose chunks that stop at marks are a program of their own takes ``masked``
    laid = hasattr(chunked, "_per_member")
    takes = inspect.signature(chunked._chunk_program).parameters
    axes = [0 if laid else None, 0 if laid and hybrid_arg is not None else None] if "params_axis" in takes else []
    masked = [True] if "masked" in takes else []
    init = start_program(p.scenarios.plant, p.rates, cfg.mode, "rest", *axes)
    chunk = chunked._chunk_program(p.scenarios.plant, p.rates, cfg.mode, *axes, *masked)
    batches = set()
    for idx, models, refs in p.scenarios.groups.values():
        if len(idx) in batches:  # the same two programs (a batch of this size, any path length): compiled once
            continue
        batches.add(len(idx))
        refs = jax.tree.map(np.asarray, refs)
        piece = jax.tree.map(lambda x: np.pad(x[:, :chunked.CHUNK], [(0, 0), (0, max(chunked.CHUNK - x.shape[1], 0))]
                                              + [(0, 0)] * (x.ndim - 2), mode="edge"), refs)
        gains = [chunked._per_member(g, None, len(idx)) for g in (servo, hybrid_arg)] if laid else [servo, hybrid_arg]
        first = (gains[0], models, jax.tree.map(lambda x: x[:, 0], refs), gains[1], None)
        # programs kept on disk (pusupu_jax.programs.Program): their compiled calls take the arguments' leaves
        if hasattr(init, "rest"):
            if hasattr(init.rest, "lower"):
                rest = timed(lambda: init.rest.lower(gains[0], models))(*jax.tree.leaves((gains[0], models)))
            else:  # the rest a member at a time through one program: its first call traces, compiles and runs it
                t = time.perf_counter()
                rest = init.rest(gains[0], models)
                out["forward_compile_s"] += time.perf_counter() - t
            carry = timed(lambda: init.finish.lower(*first, rest))(*jax.tree.leaves((*first, rest)))
        else:
            carry = timed(lambda: init.lower(*first))(*jax.tree.leaves(first))
        timed(lambda: chunk.lower(gains[0], models, piece, gains[1], None, carry, np.int32(1)))
p.refresh(z0)
ones = {k: jnp.ones(p.rows) for k in objectives.TERMS}
t = time.perf_counter()
args = (z0, ones, p.starts, p.windows)
lowered = p._value_and_grad.lower(*args)  # a tree with pusupu_jax.programs: the trace includes the export and write
out["gradient_trace_s"] = time.perf_counter() - t
if hasattr(p._value_and_grad, "loaded"):  # a pusupu_jax.programs.Program: its compiled call takes the leaves
    args = jax.tree.leaves(args)
t = time.perf_counter()
compiled = lowered.compile()
out["gradient_compile_s"] = time.perf_counter() - t
for key in ("gradient_first_run_s", "gradient_run_s"):
    t = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    out[key] = time.perf_counter() - t
out["trace_and_compile_s"] = sum(out[k] for k in ("forward_trace_s", "forward_compile_s", "gradient_trace_s",
                                                  "gradient_compile_s"))
print(json.dumps(out))
"""
)


def measure(tree: Path, config: str, xla_flags: str = "") -> dict:
    """One cold measurement of ``tree`` in a fresh interpreter with an empty compile cache (and ``xla_flags`` added
    to ``XLA_FLAGS``)."""
    with tempfile.TemporaryDirectory(prefix="pusupu-cold-") as cache:
        env = dict(os.environ, PYTHONPATH=str(tree), XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} {xla_flags}".strip())
        env.pop("PUSUPU_JAX_CACHE", None)
        done = subprocess.run(
            [sys.executable, "-c", CHILD, config, cache, str(tree)],
            env=env,
            cwd=tree,
            capture_output=True,
            text=True,
            timeout=3600,
        )
    if done.returncode:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"bench_cold_start: the run in {tree} failed: {last}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--config",
        default="default",
        choices=("default", "quick"),
        help="TuneConfig() (what plain `pusupu tune` runs) or TuneConfig.quick()",
    )
    ap.add_argument("--against", type=Path, help="another source tree to measure the same way")
    ap.add_argument(
        "--xla-flags",
        action="append",
        default=[],
        metavar="FLAGS",
        help="also measure this tree with FLAGS added to XLA_FLAGS (repeatable)",
    )
    ap.add_argument("--repeat", type=int, default=1, help="cold runs of each tree, alternating")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error(f"--repeat: expected at least 1 run, got {args.repeat}")
    if args.against and not (args.against / "pusupu_jax").is_dir():
        ap.error(f"--against: expected a source tree with pusupu_jax/, got {args.against}")
    here = Path(__file__).resolve().parent.parent
    trees = {"this": (here, "")} | ({"against": (args.against.resolve(), "")} if args.against else {})
    trees |= {f"this {flags}": (here, flags) for flags in args.xla_flags}
    runs = {name: [] for name in trees}
    for r in range(args.repeat):
        for name, (tree, flags) in trees.items():
            runs[name].append(measure(tree, args.config, flags))
            print(
                f"bench_cold_start: {name} run {r + 1}/{args.repeat}: trace and compile "
                f"{runs[name][-1]['trace_and_compile_s']:.1f} s",
                file=sys.stderr,
                flush=True,
            )
    result = {
        "benchmark": "cold_start",
        "config": args.config,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "trees": {k: str(v[0]) for k, v in trees.items()},
        "runs": runs,
        "median_trace_and_compile_s": {
            k: sorted(r["trace_and_compile_s"] for r in v)[len(v) // 2] for k, v in runs.items()
        },
    }
    if args.against:
        m = result["median_trace_and_compile_s"]
        result["ratio_this_over_against"] = m["this"] / m["against"]
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
