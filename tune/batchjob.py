"""``pusupu batch JOB.yaml --out DIR``: every job of a job file, in shards, in this process or as Ray tasks.

Jobs that compile to the same shapes (:func:`pusupu_jax.tune.jobfile.groups`) are cut into shards of at
most ``shard_size`` jobs, padded to equal size (so that one compile serves every shard of a
group).  A shard is one call of :func:`run_shard`: one :class:`pusupu_jax.tune.batch.BatchProblem`, its
checkpoint in ``DIR/shards/<id>/checkpoint.npz`` (a shard that is run again, or retried by Ray,
continues from it), and each job's outputs in ``DIR/jobs/<job>/``: ``gains.yaml`` and the ROS 2
files (only if the gains pass every check), plots, and last ``report.json``, which names the
job's digest.  A job whose ``report.json`` carries its digest is done and is skipped when the
batch runs again.  Last, ``DIR/summary.csv``, ``summary.md``, ``summary.json`` and
``summary.png`` cover every job, the failed ones marked with their error.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

from pusupu_jax import devices as placement, inputs, machine_file
from pusupu_jax.files import write_atomic
from pusupu_jax.runtime import setup_jax
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import ParameterError

from . import jobfile
from .config import TuneConfig
from .report import JobReport, JobStatus, SummaryRow, metrics_json

SUMMARY_FILES = ("summary.csv", "summary.md", "summary.json", "summary.png")
MAX_REPORT_BYTES = 64 << 20  # a job's report.json: its history, a few hundred bytes an iteration


def job_dir(out: Path, name: str) -> Path:
    return Path(out) / "jobs" / name.replace("/", "_")


def done_report(out: Path, job: jobfile.Job) -> dict | None:
    """The job's ``report.json`` (:class:`~pusupu_jax.tune.report.JobReport`'s JSON) if a finished run of these very
    settings wrote it, else None."""
    path = job_dir(out, job.name) / "report.json"
    try:
        report = json.loads(inputs.read_bytes(path, "job report", ParameterError, limit=MAX_REPORT_BYTES))
    except (ValueError, RecursionError):  # none, not a regular file, too large, not JSON (ParameterError: a ValueError)
        return None
    return report if isinstance(report, dict) and report.get("job_digest") == job.digest() else None


def shards(jobs: list, shard_size: int | None) -> list[dict]:
    """The tasks of one group's pending ``jobs``: shards of at most ``shard_size`` jobs, padded to one size."""
    size = len(jobs) if shard_size is None else min(shard_size, len(jobs))
    cfg = jobs[0].config
    config = cfg.to_json()
    tasks = []
    for a in range(0, len(jobs), size):
        part = jobs[a : a + size]
        entries = [
            {"name": j.name, "digest": j.digest(), "specs": [jobfile.spec_dict(s) for s in j.specs]} for j in part
        ]
        pad = size - len(part)
        ident = hashlib.sha256(json.dumps([[e["digest"] for e in entries], pad]).encode()).hexdigest()[:12]
        machine = None if part[0].machine is None else part[0].machine.content()
        tasks.append({"id": ident, "config": config, "jobs": entries, "pad": pad, "machine": machine})
    return tasks


def run_shard(task: dict, out: str, plots: bool = True, stream=None) -> list[dict]:
    """Tune one shard's jobs in one vmapped batch; write each job's outputs; return their summary rows.

    Callable in this process or as a Ray task (it sets JAX up itself, and everything it takes and returns is
    plain data).  Its pid is in ``DIR/shards/<id>/worker.pid`` while it runs.
    """
    setup_jax()
    from .batch import BatchProblem, lay_out, optimise_batch
    from .job import start_gains

    stream = stream or sys.stderr
    out = Path(out)
    folder = out / "shards" / task["id"]
    folder.mkdir(parents=True, exist_ok=True)
    write_atomic(folder / "worker.pid", str(os.getpid()))
    cfg = TuneConfig().replace(**task["config"])
    entries = task["jobs"] + [task["jobs"][-1]] * task["pad"]
    specs, problems = lay_out([[jobfile.spec_from_dict(d) for d in e["specs"]] for e in entries])
    n_jobs = len(task["jobs"])
    t0 = time.perf_counter()
    padding = f", {task['pad']} padding" if task["pad"] else ""
    print(
        f"batch: shard {task['id']}: {n_jobs} job(s) x {cfg.starts} start(s) "
        f"({len(specs)} scenario runs{padding}); compiling",
        file=stream,
        flush=True,
    )
    machine = Machine.default() if task["machine"] is None else machine_file.parse(task["machine"])
    servo0, hybrid0, start = start_gains(machine, None, stream)
    problem = BatchProblem(cfg, specs, problems, servo0, hybrid0, machine=machine)
    result = optimise_batch(
        problem, checkpoint=folder / "checkpoint.npz", digest=task["id"], progress=progress_printer(task["id"], stream)
    )
    R = cfg.starts
    best_members = []
    for j in range(n_jobs):
        members = [m for m in range(j * R, (j + 1) * R) if m not in result.failed]
        best_members.append(min(members, key=lambda m: result.best_value[m]) if members else None)
    z0 = problem.z0()
    zb = {k: np.array(v) for k, v in z0.items()}
    for j, m in enumerate(best_members):
        if m is not None:
            for k in zb:
                zb[k][j * R] = result.best_z[k][m]
    before, after = problem.path_metrics(z0), problem.path_metrics(zb)
    rows = []
    for j, e in enumerate(task["jobs"]):
        m = best_members[j]
        history = [h for mm in range(j * R, (j + 1) * R) for h in result.history[mm]]
        failed = {mm - j * R: result.failed[mm] for mm in range(j * R, (j + 1) * R) if mm in result.failed}
        rows.append(
            write_job(
                out,
                e,
                cfg,
                problem,
                None if m is None else problem.member_z(zb, j * R),
                history,
                failed,
                before[j * R],
                after[j * R],
                plots,
                machine,
                start,
                problem.loads[j],
                stream,
            )
        )
    print(f"batch: shard {task['id']} done in {time.perf_counter() - t0:.0f} s", file=stream, flush=True)
    return rows


def write_job(
    out: Path,
    entry: dict,
    cfg: TuneConfig,
    problem,
    z,
    history,
    failed,
    before,
    after,
    plots: bool,
    machine: Machine,
    start: dict,
    loads: dict,
    stream=sys.stderr,
) -> dict:
    """One job's outputs on ``machine`` from the start gains ``start`` (what the report says of them): gains and ROS 2
    files if they pass every check (with each of its margin ``loads``, :func:`pusupu_jax.machine_file.margin_loads`),
    plots, report.json last; its summary row.  Where ROS's PID with the exported gains keeps less than the floors,
    one warning line on ``stream`` names the job (the report keeps it as ``ros_warning``)."""
    from .job import _plots, export

    folder = job_dir(out, entry["name"])
    folder.mkdir(parents=True, exist_ok=True)
    first = [h for h in history if h.iteration == 0 and h.start == 0]
    objective_before = first[0].objective if first else float("nan")
    common = dict(
        job=entry["name"],
        job_digest=entry["digest"],
        scenarios=entry["specs"],
        machine=machine_file.reference(machine),
        start_gains=start,
        config=cfg.to_json(),
        tuned_fields=list(problem.space.fields),
        failed_starts={str(k): v for k, v in failed.items()},
        history=[h.without_point() for h in history],
        objective_before=objective_before,
        before={n: r for n, (r, _) in before.items()},
    )
    if z is None:
        report = JobReport(**common, status=JobStatus.FAILED, error="every start failed: " + "; ".join(failed.values()))
    else:
        servo, hybrid = problem.space.host_values(z)
        best = min(h.objective for h in history)
        metrics_after = {n: r for n, (r, _) in after.items()}
        provenance = {
            "config_hash": cfg.digest(),
            "job": entry["name"],
            "job_digest": entry["digest"],
            "objective_before": objective_before,
            "objective_after": best,
            "floors": [cfg.pm_min, cfg.gm_min],
            "metrics_after": metrics_json(metrics_after),
        }
        outcome = export(folder, cfg, servo, hybrid, problem.rates, problem.space.fields, provenance, machine, loads)
        if outcome.ros_warning is not None:
            print(f"batch: warning: job {entry['name']}: {outcome.ros_warning}", file=stream, flush=True)
        report = JobReport(
            **common,
            status=JobStatus.OK if outcome.error is None else JobStatus.NOT_EXPORTED,
            error=outcome.error or "",
            objective_after=best,
            after=metrics_after,
            start=problem.space.json_values(problem.space.z0()),
            result=problem.space.json_values(z),
            export=outcome,
            plots=_plots(folder, history, before, after, {}) if plots else None,
        )
    text = report.to_json()
    write_atomic(folder / "report.json", json.dumps(text, indent=2))
    return text["row"]


def progress_printer(shard: str, stream=sys.stderr) -> Callable:
    """The progress callback of a shard (:class:`pusupu_jax.tune.progress.Progress`): the median and best objective over
    its
    members."""
    from .progress import Progress

    report = Progress(stream)

    def progress(iteration, iterations, values, elapsed):
        finite = values[np.isfinite(values)]
        summary = f"J median {np.median(finite):.4f} best {finite.min():.4f}" if finite.size else "J nan"
        report(iteration, iterations, elapsed, f"batch [shard {shard}]", f"{summary} over {len(values)} member(s)")

    return progress


def run_batch(
    path,
    out,
    *,
    ray: bool = False,
    address: str | None = None,
    workers: int | None = None,
    cpus_per_task: int = 1,
    fresh: bool = False,
    stream=sys.stderr,
    device: str | None = None,
) -> tuple[dict, int]:
    """Run a job file; returns ``(summary, exit status)``: 0 when every job exported gains, 1 otherwise.  ``device``:
    where this process computes (:func:`pusupu_jax.devices.choose`: ``auto`` by the widest shard's rows), or None for
    JAX's default (Ray's tasks take a GPU where the cluster has one).  ``cpus_per_task``: the CPUs (and XLA host
    devices) a Ray task asks for where the cluster has no GPU."""
    from .job import OutputLock, prepare_output

    jf = jobfile.read(path)
    if device is not None:
        ok = [j for j in jf.jobs if j.error is None]
        rows = max((j.config.starts * len(j.specs) * j.config.windows for j in ok), default=1)
        members = max(1, min(jf.shard_size or len(ok), len(ok)))
        placement.choose(device, rows * members, f"{members} job(s) x {rows} windows")
    out = prepare_output(Path(out), SUMMARY_FILES)
    lock = OutputLock(out)
    try:
        if fresh:
            for sub in ("shards", "jobs"):
                shutil.rmtree(out / sub, ignore_errors=True)
        rows = {j.name: SummaryRow.unread(j.name, j.error) for j in jf.jobs if j.error is not None}
        unreadable, tasks = len(rows), []
        for jobs in jobfile.groups(jf.jobs).values():
            pending = []
            for j in jobs:
                report = done_report(out, j)
                if report is None:
                    pending.append(j)
                else:
                    rows[j.name] = SummaryRow.from_json(report["row"])
            if pending:
                tasks += shards(pending, jf.shard_size)
        placement.announce(stream)
        print(
            f"batch: {len(jf.jobs)} job(s) ({jf.problems}), {unreadable} failed to read, {len(rows) - unreadable} done "
            f"before, {len(tasks)} shard(s) to run" + (" as Ray tasks" if ray else ""),
            file=stream,
            flush=True,
        )
        if ray:
            from .cluster import run_tasks

            results = run_tasks(
                run_shard,
                tasks,
                out,
                plots=jf.plots,
                address=address,
                workers=workers,
                cpus_per_task=cpus_per_task,
                stream=stream,
            )
        else:
            results = []
            for k, task in enumerate(tasks):
                results.append(run_shard(task, str(out), jf.plots, stream))
                print(f"batch: {k + 1}/{len(tasks)} shard(s) done", file=stream, flush=True)
        for task_rows in results:
            for row in map(SummaryRow.from_json, task_rows):
                rows[row.job] = row
        ordered = [rows[j.name] for j in jf.jobs]
        summary = write_summary(out, ordered)
        return summary, 0 if all(r.status is JobStatus.OK for r in ordered) else 1
    finally:
        lock.release()


def write_summary(out: Path, rows: list[SummaryRow]) -> dict:
    """``summary.csv``, ``summary.md``, ``summary.json`` and ``summary.png`` over every job; returns
    ``summary.json``'s content."""
    fields = sorted({k for r in rows for k in r.gains})
    columns = list(SummaryRow.COLUMNS[:-1]) + fields + ["error"]
    plain = [r.to_json() for r in rows]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in plain:
        writer.writerow({c: _fmt(r.get(c, "")) for c in columns})
    write_atomic(out / "summary.csv", buffer.getvalue())
    write_atomic(out / "summary.md", markdown(plain, columns))
    summary = {
        "jobs": len(rows),
        "ok": sum(r.status is JobStatus.OK for r in rows),
        "failed": [r.job for r in rows if r.status is not JobStatus.OK],
        "rows": plain,
    }
    write_atomic(out / "summary.json", json.dumps(summary, indent=2))
    summary_plot(out / "summary.png", rows, fields)
    return summary


def _fmt(v):
    return f"{v:.6g}" if isinstance(v, float) else v


def markdown(rows: list[dict], columns) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        lines.append("| " + " | ".join(str(_fmt(r.get(c, ""))).replace("|", "/") for c in columns) + " |")
    return "\n".join(lines) + "\n"


def summary_plot(path: Path, rows: list[SummaryRow], fields: list[str]) -> None:
    """The spread over jobs of each tuned gain and of the RMS tracking error before and after."""
    import matplotlib.pyplot as plt

    from pusupu_jax.plots import save_atomic

    ok = [r.to_json() for r in rows if r.status is JobStatus.OK]
    panels = fields + ["rms_before_mm", "rms_after_mm"]
    fig, axes = plt.subplots(1, len(panels), figsize=(2.2 * len(panels) + 1, 4), squeeze=False)
    rng = np.random.default_rng(0)
    for ax, key in zip(axes[0], panels):
        values = [r[key] for r in ok if isinstance(r.get(key), float) and np.isfinite(r[key])]
        ax.boxplot(values or [np.nan], widths=0.5, showfliers=False)
        ax.plot(1 + rng.uniform(-0.15, 0.15, len(values)), values, ".", alpha=0.6)
        ax.set_title(key, fontsize=9)
        ax.set_xticks([])
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"spread over {len(ok)} job(s) that exported gains ({len(rows) - len(ok)} not)")
    fig.tight_layout()
    save_atomic(fig, path)
    plt.close(fig)
