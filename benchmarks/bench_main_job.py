"""The main job, ``pusupu tune`` with the embedded configuration: its first iteration cold and warm, and its steady
iterations, on each device and CPU set given, one run after another (JSON on stdout).

The job is frozen: ``TuneConfig()`` (its digest is in the output), cut to ``--iterations`` iterations (default 6,
so the steady iterations 2..6 include one renewal of the windows' start states, every ``refresh_every`` = 5, as the
whole job's do).  Each run is a fresh interpreter that builds the problem and runs the optimiser as ``pusupu tune``
does; it reports the time from its start (imports included) to the end of the first iteration, and the mean of the
later ones.  The first iteration is taken apart with JAX's own timings (``jax.monitoring``): tracing, lowering to
StableHLO and XLA's compile (a cache hit's load included), per program for the eight costliest, the cache loads as a
total, and the rest (running, Python, imports).  ``--calls`` takes the rest apart too: each stored program's calls
(:class:`pusupu_jax.programs.Program`; each waited for, a first call's compile included) and the forward passes over
the whole paths that give the windows their start states (``Problem.refresh``), to the end of the first iteration.
A *cold* run has an empty compilation cache (and so no stored traced
programs); the *warm* run after it uses the cache the cold one filled.

A configuration is ``LABEL=PLATFORM[@CPUS]``: ``cpu2=cpu@0-1`` runs on the CPU pinned to CPUs 0-1 (``taskset``),
``gpu=gpu`` on the GPU (JAX's default device), ``host=auto`` where ``pusupu tune``'s ``--device auto`` puts the job
(:func:`pusupu_jax.devices.select`, with every backend visible; ``auto_chose`` in the output says which and why).
``--against DIR`` runs each configuration also with another source tree (``git archive`` of another commit unpacked
there), alternating (each round in the reverse order of the one before), so that both see the same machine::

    python benchmarks/bench_main_job.py --configs cpu2=cpu@0-1,cpu14=cpu@2-15,gpu=gpu [--against DIR] [--repeat 1]

``--whole`` runs the whole job instead, as a user runs it: the tree's own ``pusupu`` command (the entry point and
package folders its ``pyproject.toml`` names, so a tree of another layout runs too) with no arguments but ``tune
--out``, from an empty compilation cache, and reports its wall time, its CPU time and its result (the end of its
output)::

    python benchmarks/bench_main_job.py --whole --configs cpu2=cpu --against DIR --repeat 2

``--xla-flags FLAGS`` runs each configuration of each tree also with ``FLAGS`` added to ``XLA_FLAGS`` (the runs named
``this+flags`` and ``against+flags``), alternating with the runs without them, so that a flag is judged on one
machine::

    python benchmarks/bench_main_job.py --configs cpu2=cpu@0-1,cpu14=cpu@2-15 \\
        --xla-flags=--xla_llvm_disable_expensive_passes=true
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from timing import MOUNT_TREE, parse_config, pinned, processor  # beside this script

CHILD = (
    r"""
import time
t0 = time.perf_counter()
"""
    + MOUNT_TREE
    + r"""
import json
from collections import defaultdict
from pusupu_jax.runtime import setup_jax
setup_jax(sys.argv[1])
import jax
from jax import monitoring

events = []  # (seconds from start, event, function, duration): JAX's own trace, lowering and compile timings


def on_duration(event, duration, **kw):
    events.append((time.perf_counter() - t0, event.rsplit("/", 1)[-1], kw.get("fun_name", ""), duration))


monitoring.register_event_duration_secs_listener(on_duration)
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import ServoParams
from pusupu_jax.tune.config import TuneConfig
from pusupu_jax.tune.run import Problem

# with --calls: each stored program's calls to the end of the first iteration (waited for, the first call's compile
# included), and the forward passes over the whole paths that give the windows their start states
calls = defaultdict(lambda: {"calls": 0, "s": 0.0})
if sys.argv[3] == "calls":
    from pusupu_jax import programs

    def timed(method, name_of):
        def call(self, *args):
            a = time.perf_counter()
            out = jax.block_until_ready(method(self, *args))
            if not ends:
                c = calls[name_of(self)]
                c["calls"] += 1
                c["s"] += time.perf_counter() - a
            return out
        return call

    programs.Program.__call__ = timed(programs.Program.__call__, lambda self: getattr(self.fun, "__qualname__", "?"))
    Problem.refresh = timed(Problem.refresh, lambda self: "Problem.refresh (the forward pass over the whole paths)")

cfg = TuneConfig()
digest = cfg.digest()
cfg = cfg.replace(iterations=int(sys.argv[2]), checkpoint_every=int(sys.argv[2]) * 5)
chosen = None
if sys.argv[4] == "auto":  # as pusupu tune chooses (pusupu_cli/tuning.py), before any computation
    from pusupu_jax import devices

    scenarios = len(cfg.trajectories) * len(cfg.kin_error_seeds) * len(cfg.payloads)
    chosen = devices.select("auto", scenarios * cfg.windows, f"{scenarios} scenario(s) x {cfg.windows} windows")
ends = []
cpu0 = os.times()


def progress(k, iteration, iterations, value, best, aux, elapsed):
    ends.append((time.perf_counter() - t0, value))


p = Problem(cfg, ServoParams.table1(), HybridGains())
result = p.tune(progress=progress)
cpu1 = os.times()
steady = [b[0] - a[0] for a, b in zip(ends, ends[1:])]
KIND = {"jaxpr_trace_duration": "trace_s", "jaxpr_to_mlir_module_duration": "lower_s",
        "backend_compile_duration": "compile_s", "cache_retrieval_time_sec": "cache_load_s"}
totals, programs = defaultdict(float), defaultdict(lambda: defaultdict(float))
for at, event, fun, duration in events:
    if at <= ends[0][0] and event in KIND:
        totals[KIND[event]] += duration
        if fun:  # JAX names no function for a cache load: those are a total only
            programs[fun.removeprefix("jit(").removesuffix(")")][KIND[event]] += duration
top = sorted(programs.items(), key=lambda kv: -sum(kv[1].values()))[:8]
breakdown = {k: round(totals[k], 2) for k in KIND.values()} | {
    "rest_s": round(ends[0][0] - totals["trace_s"] - totals["lower_s"] - totals["compile_s"], 2),
    "programs": {name: {k: round(v, 2) for k, v in kinds.items()} for name, kinds in top},
}
if calls:
    costliest = sorted(calls.items(), key=lambda kv: -kv[1]["s"])
    breakdown["calls"] = {k: {"calls": v["calls"], "s": round(v["s"], 2)} for k, v in costliest}
print(json.dumps({
    "config_digest": digest,
    "first_iteration_s": ends[0][0],
    "first_iteration_breakdown": breakdown,
    "steady_iteration_s": sum(steady) / len(steady),
    "steady_iterations": steady,
    "objective": [v for _, v in ends],
    "cpu_s": (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system),
    "wall_s": time.perf_counter() - t0,
    "devices": [str(d) for d in jax.devices()],
    "default_backend": jax.default_backend(),
    "auto_chose": chosen,
    "windows_over_devices": 1 if getattr(p, "mesh", None) is None else p.mesh.size,
    "sources": [pusupu_jax.__file__, sys.modules["pusupu_jax.tune.run"].__file__],
    "jax": jax.__version__,
    "jaxlib": __import__("jaxlib").__version__,
    "xla_flags": os.environ.get("XLA_FLAGS", ""),  # as the package's import left them (pusupu_jax.runtime)
}))
"""
)


WHOLE = r"""
import importlib, importlib.util, os, sys, tomllib
tree = sys.argv.pop()
with open(os.path.join(tree, "pyproject.toml"), "rb") as f:
    project = tomllib.load(f)
for name, folder in project.get("tool", {}).get("setuptools", {}).get("package-dir", {}).items():
    importlib.import_module(name.rpartition(".")[0])
    path = os.path.join(tree, folder)
    spec = importlib.util.spec_from_file_location(name, os.path.join(path, "__init__.py"),
                                                  submodule_search_locations=[path])
    sys.modules[name] = module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
entry, _, function = project["project"]["scripts"]["pusupu"].partition(":")
sys.argv[0] = "pusupu"
sys.exit(getattr(importlib.import_module(entry), function)())
"""


RESULT_LINES = 20  # of pusupu tune's stdout kept in the JSON: its table of errors, the objective, the gains


def child(tree: Path, platform_name: str, cpus: str | None, cmd: list[str], cwd: Path, what: str, **env_extra: str):
    """Run ``cmd`` with ``tree`` first on the path, on the platform and CPUs asked, in ``cwd``
    (:func:`timing.pinned`)."""
    path = os.pathsep.join(filter(None, (str(tree), os.environ.get("PYTHONPATH"))))
    return pinned(cmd, platform_name, cpus, f"bench_main_job: {what} in {tree}", cwd, PYTHONPATH=path, **env_extra)


def run_whole(tree: Path, platform_name: str, cpus: str | None, **env: str) -> dict:
    """``pusupu tune`` of ``tree`` from an empty cache (and an empty home): wall and CPU seconds, and the last lines
    of what it printed on stdout (its result)."""
    with tempfile.TemporaryDirectory(prefix="pusupu-main-job-") as scratch:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        cmd = [sys.executable, "-c", WHOLE, "tune", "--out", str(Path(scratch) / "out"), str(tree)]
        done = child(
            tree, platform_name, cpus, cmd, Path(scratch), "pusupu tune", PUSUPU_JAX_CACHE=scratch, HOME=scratch, **env
        )
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {
        "wall_s": round(wall, 1),
        "user_s": round(after.ru_utime - before.ru_utime, 1),
        "system_s": round(after.ru_stime - before.ru_stime, 1),
        "result": done.stdout.strip().splitlines()[-RESULT_LINES:],
    }


def run(tree: Path, cache: str, platform_name: str, cpus: str | None, iterations: int, calls: bool, **env: str) -> dict:
    cmd = [sys.executable, "-c", CHILD, cache, str(iterations), "calls" if calls else "-", platform_name, str(tree)]
    done = child(tree, platform_name, cpus, cmd, tree, "the run", **env)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="cpu=cpu", help="comma-separated LABEL=PLATFORM[@CPUS] (default cpu=cpu)")
    ap.add_argument("--against", type=Path, help="another source tree to measure the same way, alternating")
    ap.add_argument("--iterations", type=int, default=6, help="iterations of each run (at least 2)")
    ap.add_argument("--repeat", type=int, default=1, help="cold + warm pairs of each configuration and tree")
    ap.add_argument("--no-warm", action="store_true", help="cold runs only")
    ap.add_argument("--whole", action="store_true", help="the whole pusupu tune of each tree, cold (wall, CPU)")
    ap.add_argument(
        "--calls",
        action="store_true",
        help="also time each stored program's calls and the forward passes over the whole paths, to the end of the "
        "first iteration (each call waited for)",
    )
    ap.add_argument(
        "--xla-flags",
        metavar="FLAGS",
        help="also run each configuration of each tree with FLAGS added to XLA_FLAGS, alternating (runs '+flags')",
    )
    ap.add_argument("--out", type=Path, help="write the JSON here, after every run, instead of on stdout at the end")
    args = ap.parse_args()
    if args.iterations < 2:
        ap.error(f"--iterations: expected at least 2, got {args.iterations}")
    configs = {}
    for item in args.configs.split(","):
        try:
            label, name, cpus = parse_config(item, ("cpu", "gpu", "auto"))
        except SystemExit as e:
            ap.error(f"--configs: {e}")
        configs[label] = (name, cpus)
    here = Path(__file__).resolve().parent.parent
    trees = {"this": here} | ({"against": args.against.resolve()} if args.against else {})
    variants = {"": {}} | (
        {"+flags": {"XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} {args.xla_flags}".strip()}}
        if args.xla_flags
        else {}
    )
    runs: dict = {f"{t}{v} {c}": [] for c in configs for t in trees for v in variants}
    for r in range(args.repeat):
        for label, (name, cpus) in configs.items():
            order = list(itertools.product(trees.items(), variants.items()))
            for (tree_base, tree), (variant, env) in order if r % 2 == 0 else reversed(order):  # ABBA over rounds
                tree_name = tree_base + variant
                if args.whole:
                    runs[f"{tree_name} {label}"].append(whole := run_whole(tree, name, cpus, **env))
                    if args.out:
                        write(args, configs, trees, runs)
                    print(f"bench_main_job: {tree_name} {label} round {r + 1}: {whole}", file=sys.stderr, flush=True)
                    continue
                with tempfile.TemporaryDirectory(prefix="pusupu-main-job-") as cache:
                    cold = run(tree, cache, name, cpus, args.iterations, args.calls, **env)
                    warm = None if args.no_warm else run(tree, cache, name, cpus, args.iterations, args.calls, **env)
                runs[f"{tree_name} {label}"].append({"cold": cold, "warm": warm})
                if args.out:
                    write(args, configs, trees, runs)
                print(
                    f"bench_main_job: {tree_name} {label} round {r + 1}: first iteration cold "
                    f"{cold['first_iteration_s']:.1f} s"
                    + ("" if warm is None else f", warm {warm['first_iteration_s']:.1f} s")
                    + f", steady {cold['steady_iteration_s']:.2f} s/it",
                    file=sys.stderr,
                    flush=True,
                )
    write(args, configs, trees, runs)


def write(args, configs, trees, runs) -> None:
    """The JSON so far: on stdout at the end, and into ``--out`` after every run (a partial campaign keeps what ran)."""
    text = json.dumps(
        {
            "benchmark": "main_job",
            "job": "pusupu tune, whole, cold"
            if args.whole
            else "TuneConfig() (pusupu tune's embedded configuration), cut to --iterations",
            "iterations": None if args.whole else args.iterations,
            "configs": {k: {"platform": v[0], "cpus": v[1]} for k, v in configs.items()},
            "xla_flags": {"inherited": os.environ.get("XLA_FLAGS", ""), "+flags": args.xla_flags},
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "processor": processor(),
            "trees": {k: describe(v) for k, v in trees.items()},
            "runs": runs,
        },
        indent=1,
    )
    if args.out:
        args.out.write_text(text)
    else:
        print(text)


def describe(tree: Path) -> dict:
    """The tree's folder and, where it is a git checkout, its commit and whether it has changes."""
    head = subprocess.run(["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(tree), "status", "--porcelain"], capture_output=True, text=True)
    found = head.returncode == 0 and Path(tree, ".git").exists()
    return {
        "path": str(tree),
        "commit": head.stdout.strip() if found else None,
        "changes": bool(dirty.stdout.strip()) if found else None,
    }


if __name__ == "__main__":
    main()
