"""Batch tuning throughput: one tuning iteration of B independent scenarios in one vmapped gradient (JSON on stdout).

Runs :func:`pusupu_jax.tune.batch.optimise_batch` (what ``pusupu batch`` runs per shard: the vmapped
gradient, the vmapped optax update, the window refresh every ``--refresh-every`` iterations and
the host-side bookkeeping) on B independent problems, for each B of ``--batches``.  The
scenarios cycle over ``--distinct`` kinematic-error seeds on both paths (building thousands of
distinct MuJoCo models would only time the host), so every member computes its own rollouts
and gradient.  The first iteration (trace, compile, first run) is reported apart; the
iteration time is the median of the others, and the mean, which spreads the refreshes.

    python benchmarks/bench_batch.py [--batches 1,2,64] [--iterations 6] [--path 0.2] [--window 0.05] [--windows 1]
                                     [--devices N] [--remat] [--label NAME] [--parts N] [--out FILE]

``scenario_iterations_per_s`` = B / iteration time; ``peak_device_bytes``, the most memory the devices held at once
since the process started (the largest over the devices, from ``Device.memory_stats``; none on a CPU), so a batch
size's own peak needs a process of its own; ``max_rss_bytes``, the host process's peak resident memory;
``rows`` = B x ``--windows``, the rollouts of one gradient (the width ``--device auto``
compares with :data:`pusupu_jax.devices.GPU_CROSSOVER_ROWS`).  The default tune's windows are
``--path 3 --window 0.5 --windows 6``.

``--run LABEL=PLATFORM[@CPUS]:BATCHES[:remat]`` (repeated) compares devices in one run: the script runs itself once
per ``--run``, one after another in the order given (never side by side), each on its platform (``taskset`` on its
CPUs) with its batch sizes, an empty compilation cache and the other options as given, and reports every run's rows,
each run's best throughput and its ratio to the first run's best::

    python benchmarks/bench_batch.py --path 3 --window 0.5 --windows 6 --iterations 4 \
        --run cpu2=cpu@0-1:1,2,8 --run gpu=gpu:1024 --run gpu_remat=gpu:4096:remat --out FILE

With ``--devices N`` the batch is sharded
over the first N devices (``jax.sharding``), as ``pusupu batch`` does over all of them; ``--remat`` sets the
configuration's ``remat`` (reverse mode keeps one carry per position period and runs each period again; on an
H200 it did not bring batch 4096 into memory before the margins' fix, and is not needed for it since).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

from timing import median_time, parse_config, pinned, processor  # beside this script

SHARED = ("iterations", "refresh_every", "path", "window", "windows", "distinct", "parts")  # what every --run takes


def parse_run(item: str) -> tuple[str, str, str | None, str, bool]:
    """``LABEL=PLATFORM[@CPUS]:BATCHES[:remat]`` as ``(label, platform, cpus, batches, remat)``."""
    config, _, rest = item.partition(":")
    batches, _, flag = rest.partition(":")
    label, name, cpus = parse_config(config)
    if not batches or not all(b.isdigit() and int(b) > 0 for b in batches.split(",")) or flag not in ("", "remat"):
        raise SystemExit(f"--run: expected LABEL=PLATFORM[@CPUS]:B[,B...][:remat], got {item!r}")
    return label, name, cpus, batches, flag == "remat"


def compare(args) -> None:
    """Every ``--run`` in turn, each a fresh process of this script from an empty cache; the JSON (on stdout, and
    into ``--out`` after every run) holds each run's report (or its failure and the rows it wrote before it),
    each run's best throughput and its ratio to the first's."""
    runs = [parse_run(item) for item in args.run]
    result: dict = {
        "benchmark": "bench_batch",
        "label": args.label,
        "command": " ".join(sys.argv),
        "machine": platform.node(),
        "processor": processor(),
        "order": [label for label, *_ in runs],
        "runs": {},
    }
    for label, name, cpus, batches, remat in runs:
        with tempfile.TemporaryDirectory(prefix="pusupu-bench-batch-") as scratch:
            out = Path(scratch) / "run.json"
            cmd = [sys.executable, __file__, "--batches", batches, "--label", label, "--out", str(out)]
            cmd += [f"--{k.replace('_', '-')}={getattr(args, k)}" for k in SHARED] + (
                ["--remat"] if remat or args.remat else []
            )
            try:
                pinned(cmd, name, cpus, f"bench_batch: {label}", PUSUPU_JAX_CACHE=str(Path(scratch) / "cache"))
                failure = None
            except SystemExit as e:
                failure = str(e)
            report = json.loads(out.read_text()) if out.exists() else {"results": []}
        result["runs"][label] = report | {"cpus_pinned": cpus, "failed": failure}
        best = {
            label: max(run["results"], key=lambda r: r["scenario_iterations_per_s"])
            for label, run in result["runs"].items()
            if run["results"]
        }
        result["best"] = {
            k: {"batch": r["batch"], "scenario_iterations_per_s": r["scenario_iterations_per_s"]}
            for k, r in best.items()
        }
        first = best.get(result["order"][0])
        result["ratio_to_first"] = (
            {k: r["scenario_iterations_per_s"] / first["scenario_iterations_per_s"] for k, r in best.items()}
            if first
            else {}
        )
        print(f"bench_batch: {label}: {failure or 'done'}; best so far {result['best']}", file=sys.stderr, flush=True)
        if args.out:
            from pusupu_jax.files import write_atomic

            write_atomic(args.out, json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


def parts(problem, n: int) -> dict:
    """The iteration's two device programs timed alone, ``n`` calls each after one untimed (medians [s]): the
    vmapped gradient (``gradient_s``) and the window refresh, the forward pass over the whole paths (``refresh_s``,
    run every ``--refresh-every`` iterations).  What is left of the iteration is the optax update and the host."""
    zb = problem.shard(problem.z0())

    def refresh():
        problem.refresh(zb)
        return problem.starts

    return {"gradient_s": median_time(lambda: problem.value_and_grad(zb), n), "refresh_s": median_time(refresh, n)}


def peak_device_bytes(devices) -> int | None:
    """The most bytes any of ``devices`` held at once since the process started (None where the runtime keeps no
    such count, as on the CPU)."""
    peaks = [(d.memory_stats() or {}).get("peak_bytes_in_use") for d in devices]
    return max((p for p in peaks if p is not None), default=None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", default="1,2,64", help="comma-separated batch sizes (scenarios)")
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--refresh-every", type=int, default=5)
    ap.add_argument("--path", type=float, default=0.2, help="the first seconds of each path [s]")
    ap.add_argument("--window", type=float, default=0.05, help="the training windows' length [s]")
    ap.add_argument("--windows", type=int, default=1, help="training windows per scenario")
    ap.add_argument("--distinct", type=int, default=8, help="distinct scenarios the batch cycles over")
    ap.add_argument("--devices", type=int, help="shard over the first N devices (default: all)")
    ap.add_argument("--remat", action="store_true", help="the tune configuration's remat: true")
    ap.add_argument("--label", default="", help="a name for the run in the JSON")
    ap.add_argument("--out", help="also write the JSON here, after every batch size (a run cut short keeps its rows)")
    ap.add_argument(
        "--parts",
        type=int,
        default=0,
        metavar="N",
        help="after the iterations, time the compiled gradient alone and the window refresh alone, "
        "N calls each (medians; 0: not)",
    )
    ap.add_argument(
        "--run",
        action="append",
        metavar="LABEL=PLATFORM[@CPUS]:BATCHES[:remat]",
        help="run the benchmark once per --run, one after another, and compare their best throughputs (see above)",
    )
    args = ap.parse_args()
    if args.run:
        return compare(args)
    from pusupu_jax.runtime import cpu_count, setup_jax

    setup_jax()
    import jax

    from pusupu_jax import ServoParams
    from pusupu_jax.files import write_atomic
    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.plant.model import ModelOptions
    from pusupu_jax.tune.batch import BatchProblem, optimise_batch
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.run import ScenarioSpec

    devices = jax.devices()[: args.devices] if args.devices else jax.devices()
    cfg = TuneConfig(
        windows=args.windows,
        window_s=args.window,
        iterations=args.iterations,
        refresh_every=args.refresh_every,
        checkpoint_every=args.refresh_every,
        baselines=(),
        remat=args.remat,
    )
    specs = [
        ScenarioSpec(f"{kind}/seed{s}", kind, ModelOptions(kin_error_seed=s), path_s=args.path)
        for s in range(args.distinct // 2)
        for kind in ("arc", "p2p")
    ]
    results = []

    def report() -> dict:
        return {
            "benchmark": "bench_batch",
            "label": args.label,
            "backend": jax.default_backend(),
            "devices": [str(d) for d in devices],
            "device_kind": devices[0].device_kind,
            "jax": jax.__version__,
            "x64": bool(jax.config.jax_enable_x64),
            "remat": args.remat,
            "host": platform.node(),
            "cpus": cpu_count(),
            "window_s": args.window,
            "windows": args.windows,
            "path_s": args.path,
            "iterations": args.iterations,
            "refresh_every": args.refresh_every,
            "results": results,
        }

    for B in [int(b) for b in args.batches.split(",")]:
        t0 = time.perf_counter()
        problem = BatchProblem(
            cfg, specs, [[b % len(specs)] for b in range(B)], ServoParams.table1(), HybridGains(), devices=devices
        )
        t_build = time.perf_counter() - t0
        stamps = []
        t1 = time.perf_counter()
        optimise_batch(problem, progress=lambda it, n, values, elapsed: stamps.append(time.perf_counter()))
        steps = [b - a for a, b in zip(stamps, stamps[1:])]
        med, mean = statistics.median(steps), statistics.mean(steps)
        row = {
            "batch": B,
            "rows": B * args.windows,
            "members": len(problem.members),
            "build_s": t_build,
            "first_iteration_s": stamps[0] - t1,
            "iteration_s_median": med,
            "iteration_s_mean": mean,
            "iteration_s_all": steps,
            "scenario_iterations_per_s": B / med,
            "peak_device_bytes": peak_device_bytes(devices),
            "max_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        }
        if args.parts:
            row.update(parts(problem, args.parts))
        results.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
        if args.out:
            write_atomic(args.out, json.dumps(report(), indent=2) + "\n")
    print(json.dumps(report(), indent=2))


if __name__ == "__main__":
    main()
