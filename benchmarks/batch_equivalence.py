"""A batch of many scenarios against tuning each alone: ``pusupu batch`` versus ``pusupu tune``'s optimiser (JSON).

Writes a job file of ``--scenarios`` independent problems, every one distinct (both paths, a
kinematic-error seed each, payloads of 0 to 7.5 kg), runs it with :func:`pusupu_jax.tune.batchjob.run_batch`
(one vmapped gradient for all of them, the way ``pusupu batch JOB.yaml --out DIR`` does), then
tunes each scenario alone with the same settings, seed and starts (:meth:`pusupu_jax.tune.run.Problem.tune`, what
``pusupu tune`` runs), and compares, per scenario, the objective history of every start and
iteration and every tuned gain.

    python benchmarks/batch_equivalence.py [--scenarios 64] [--out DIR] [--tolerance 1e-7] > equivalence.json

``--out DIR`` keeps the batch's folder: run again, the batch skips its finished jobs (as ``pusupu batch`` does)
and only the lone runs are repeated.  The lone runs share one trace and one compile of the gradient (Problems that
differ only in their scenarios do: :func:`pusupu_jax.tune.run._shared_gradient`).

Tolerance, relative: the computation is the same, but vmapping 2 x scenarios members changes XLA's
fusion and summation order (last-bit differences), and the Adam steps carry them on (the suite's
three-job test, tests/test_batch.py, observes 3e-10).  Exit status 1 if any scenario differs by more.
Default shape: one 0.05 s window of each path's first 0.2 s, two starts, 3 iterations: a batch of 64
then needs about 6 GiB (the reverse-mode tape of 128 members).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path


def job_document(n: int, iterations: int) -> dict:
    """``n`` distinct scenarios: arc and p2p in turn, seed k + 1, payload (k mod 4) x 2.5 kg."""
    tune = {
        "iterations": iterations,
        "refresh_every": 1,
        "checkpoint_every": iterations,
        "windows": 1,
        "window_s": 0.05,
        "starts": 2,
    }
    scenarios = [
        {
            "name": f"s{k:03d}",
            "trajectory": ("arc", "p2p")[k % 2],
            "kin_error_seed": k + 1,
            "payload": 2.5 * (k % 4),
            "path_s": 0.2,
        }
        for k in range(n)
    ]
    return {"format": "pusupu-batch-1", "problems": "independent", "plots": False, "tune": tune, "scenarios": scenarios}


def relative(a, b) -> float:
    import numpy as np

    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--tolerance", type=float, default=1e-7)
    ap.add_argument("--out", help="the batch's output folder (default: a temporary one)")
    args = ap.parse_args()
    from pusupu_jax.runtime import setup_jax

    setup_jax()
    import jax
    import numpy as np
    import yaml

    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.params import ServoParams
    from pusupu_jax.tune import jobfile
    from pusupu_jax.tune.batchjob import done_report, run_batch
    from pusupu_jax.tune.run import Problem

    folder = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="pusupu_equivalence_"))
    folder.mkdir(parents=True, exist_ok=True)
    job = folder / "job.yaml"
    job.write_text(yaml.safe_dump(job_document(args.scenarios, args.iterations), sort_keys=False))
    jobs = jobfile.read(job).jobs
    done_before = sum(done_report(folder / "out", j) is not None for j in jobs)
    t0 = time.perf_counter()
    summary, _ = run_batch(job, folder / "out")  # an --out that holds this batch's finished jobs skips them
    t_batch = time.perf_counter() - t0
    if summary["ok"] != args.scenarios:
        print(
            f"batch_equivalence: expected {args.scenarios} jobs done, got {summary['ok']} "
            f"(failed: {summary['failed']})",
            file=sys.stderr,
        )
        return 1
    rows, t_alone = [], 0.0
    for k, j in enumerate(jobs):
        t1 = time.perf_counter()
        problem = Problem(j.config, ServoParams.table1(), HybridGains(), specs=list(j.specs))
        alone = problem.tune()
        t_alone += time.perf_counter() - t1
        report = json.loads((folder / "out" / "jobs" / j.name / "report.json").read_text())
        history = relative([h["objective"] for h in report["history"]], [h.objective for h in alone.history])
        values = problem.space.values(alone.z)
        gains = max(relative(np.ravel(report["result"][f]), np.ravel(v)) for f, v in values.items())
        rows.append(
            {
                "job": j.name,
                "trajectory": j.specs[0].trajectory,
                "evaluations": len(alone.history),
                "history_rel": history,
                "gains_rel": gains,
                "alone_s": time.perf_counter() - t1,
            }
        )
        print(
            f"batch_equivalence: {k + 1}/{args.scenarios} {j.name}: history {history:.1e}, gains {gains:.1e}",
            file=sys.stderr,
            flush=True,
        )
    worst = max(max(r["history_rel"], r["gains_rel"]) for r in rows)
    print(
        json.dumps(
            {
                "benchmark": "batch_equivalence",
                "scenarios": args.scenarios,
                "backend": jax.default_backend(),
                "jax": jax.__version__,
                "host": platform.node(),
                "tune": job_document(1, args.iterations)["tune"],
                "batch_wall_s": t_batch,
                "batch_jobs_done_before": done_before,
                "alone_wall_s": t_alone,
                "tolerance_rel": args.tolerance,
                "worst_rel": worst,
                "within_tolerance": worst <= args.tolerance,
                "rows": rows,
            },
            indent=2,
        )
    )
    return 0 if worst <= args.tolerance else 1


if __name__ == "__main__":
    sys.exit(main())
