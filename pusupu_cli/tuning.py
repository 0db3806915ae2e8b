"""``pusupu tune`` and ``pusupu batch``."""

from __future__ import annotations

import json
import os


from pusupu_jax.params import ParameterError

from pusupu_jax import devices

from .common import checking, machine_of, say


def cmd_tune(args) -> int:
    from pathlib import Path

    from pusupu_jax.runtime import setup_jax

    setup_jax()
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.job import run_job
    from pusupu_jax.tune.report import table

    if not args.out:
        raise ParameterError("--out: expected a folder, got an empty name")
    cfg = TuneConfig.quick() if args.quick else TuneConfig()
    if args.config:
        with checking(f"--config {args.config}"):
            cfg = TuneConfig.load(args.config, base=cfg)
    if args.imc_form:
        cfg = cfg.replace(imc_form=args.imc_form)
    # the rows of one gradient: every window of every scenario (starts run one after another)
    scenarios = len(cfg.trajectories) * len(cfg.kin_error_seeds) * len(cfg.payloads)
    devices.choose(args.device, scenarios * cfg.windows, f"{scenarios} scenario(s) x {cfg.windows} windows")
    out = Path(args.out)
    machine = machine_of(args)
    start = args.start_gains
    if start not in (None, "table1", "derived"):
        from pusupu_jax import gains

        with checking(f"--start-gains {start}"):
            start = gains.load(start, machine=machine)
    report, status = run_job(cfg, out, fresh=args.fresh, machine=machine, start=start)
    if args.json:
        print(json.dumps(report.to_json(history=False), indent=2))
    else:
        print(table(report))
        print(f"wrote: {', '.join(report.export.exported + report.plots + [str(out / 'report.json')])}")
    if status:
        say(f"pusupu: error: {report.export.error}")
    return status


def cmd_batch(args) -> int:
    from pathlib import Path

    from pusupu_jax.runtime import setup_jax

    setup_jax()
    from pusupu_jax.tune.batchjob import run_batch

    if (args.address or args.workers or args.cpus_per_task) and not args.ray:
        raise ParameterError("--address, --workers and --cpus-per-task need --ray")
    for flag, value in (("--workers", args.workers), ("--cpus-per-task", args.cpus_per_task)):
        if value is not None and value < 1:
            raise ParameterError(f"{flag}: expected a positive number of CPUs, got {value}")
    local = None if args.address else (args.workers or os.cpu_count() or 1)  # a task asking more would never start
    if local is not None and args.cpus_per_task and args.cpus_per_task > local:
        raise ParameterError(
            f"--cpus-per-task: expected at most the local Ray instance's {local} CPUs, got {args.cpus_per_task}"
        )
    summary, status = run_batch(
        args.job,
        args.out,
        ray=args.ray,
        address=args.address,
        workers=args.workers,
        cpus_per_task=args.cpus_per_task or 1,
        fresh=args.fresh,
        device=None if args.ray else args.device,
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(Path(args.out, "summary.md").read_text(), end="")
        print(
            f"{summary['ok']} of {summary['jobs']} job(s) exported gains; wrote {args.out}/summary.csv, "
            f"summary.md, summary.json, summary.png and jobs/<job>/"
        )
    for name in summary["failed"]:
        row = next(r for r in summary["rows"] if r["job"] == name)
        say(f"pusupu: job {name}: {row['status']}: {row['error']}")
    return status
