"""``pusupu experiment``."""

from __future__ import annotations

import json
import sys
import time


from pusupu_jax import devices

from pusupu_jax.files import check_output_folder

from .common import checking, machine_of

# the widest batch an experiment simulates at once (hybrid_grid's sweep of one gain over a path)
EXPERIMENT_ROWS = 64


def cmd_experiment(args) -> int:
    from pathlib import Path

    from pusupu_jax.runtime import setup_jax

    out = Path(args.out)
    check_output_folder(out)
    devices.choose(args.device, EXPERIMENT_ROWS, f"at most {EXPERIMENT_ROWS} simulated scenarios")
    setup_jax()
    from pusupu_jax import experiments

    experiments.get(args.name)  # an unknown name fails before any work
    with checking(f"--gains {args.gains}"):  # refused for another experiment, or a bad file: before any work
        g = experiments.gain_file(args.name, args.gains)
    machine = machine_of(args) if args.machine else None
    experiments.check_machine(args.name, machine)
    devices.announce()
    print(
        f"experiment {args.name}{' (quick)' if args.quick else ''}: running (the first runs compile for about "
        "20 s per control mode)",
        file=sys.stderr,
        flush=True,
    )
    t0 = time.perf_counter()
    result, files = experiments.run_experiment(args.name, out, quick=args.quick, gains=g, machine=machine)
    if args.json:
        print(json.dumps(result.metrics, indent=2))
    else:
        print(experiments.get(args.name).table(result))
        print(f"wrote: {', '.join(str(f) for f in files)} ({time.perf_counter() - t0:.0f} s)")
    return 0
