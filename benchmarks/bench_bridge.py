"""The bridge's real-time figures on loopback against the simulated robot (JSON on stdout and in --out).

For each rate: ``pusupu sim-robot`` in its own process, then ``--runs`` bridge runs of ``--seconds``
each (one robot session per run), with the real-time settings the OS grants.  Per run: cycles,
missed deadlines, the latency percentiles (wake-up to command sent, us), the feedback age and
whether the run completed; over the runs the spread (min, median, max) of each.

* 1 kHz: Table 1 gains, IMC on all six axes, every drive in CSV (the bridge closes the position loop);
* 4 kHz: Table 1 gains, hybrid mode: branches 1-5 CSV, branch 6 CST (the bridge closes its velocity loop at
  4 kHz and its force law at 1 kHz).

    python benchmarks/bench_bridge.py [--seconds 60] [--runs 3] [--rates 1000,4000] [--transport udp|can]
                                      [--watchdog N] [--pause-probe] [--log [on|alternate]] [--out FILE]

``steal_ms_per_cpu``: per CPU, the time the hypervisor gave it to others during the run (``/proc/stat``, 10 ms
ticks), a stall no setting inside the VM prevents; ``robot_stalls``: the simulated robot's own reports of its
serving loop not turning for more than 5 ms, with the steal on each CPU since its previous report.

``--pause-probe``: during each run, :class:`timing.PauseProbe` (a real-time sleeper on each CPU above the bridge and
the robot) records the intervals in which every CPU stopped at once; each run gets ``pauses`` and
``pauses_in_last_s`` (those that began in the last second of the run, which a stop on a fault ends 55 cycles
after the fault).  For diagnosis: the probe's wake-ups take a little from the bridge's latency.

``--log``: after each run, its MCAP log is written as ``pusupu bridge --log`` writes it (from the run's record, after
the run: the cycles run the same code with or without it); each run gets ``log_write_s`` (the wall time of that
write), ``log_bytes`` and ``log_bytes_per_s`` (per second of the cycles run).  ``--log alternate`` runs ``--runs``
runs each way in the order without, with, with, without, ... (so that each way follows another run as often as it
follows a log's write, a pause of seconds: ``after_log_write``), and compares their missed deadlines and latencies
by the way they ran (``by_log``) and by what came before them (``by_previous``).
Every run gives ``record_us``: the percentiles of the time its record (what the log is written from) took inside
each cycle with a fresh sample, all of logging's work inside a cycle.

``--transport can``: the six drives as CANopen nodes on python-can's udp_multicast bus (SDO set-up, RPDO +
SYNC, two TPDOs per drive).

The path (the arc, 26 s) repeats its last sample once done: the machine then holds still.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pusupu_jax.runtime import apply_xla_workaround, setup_jax
from timing import PauseProbe, emit, percentile_spreads, spread, steal_ms_since  # beside this script


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--rates", default="1000,4000")
    ap.add_argument("--transport", choices=("udp", "can"), default="udp")
    ap.add_argument(
        "--watchdog",
        type=int,
        default=5,
        metavar="N",
        help="the bridge's watchdog: cycles without fresh feedback before a safe stop (pusupu bridge's default)",
    )
    ap.add_argument("--pause-probe", action="store_true", help="record whole-machine pauses during each run")
    ap.add_argument(
        "--log",
        nargs="?",
        const="on",
        default="off",
        choices=("off", "on", "alternate"),
        help="write each run's MCAP log after it, time it and size it (on); or every other run, starting without "
        "(alternate: --runs runs each way)",
    )
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    apply_xla_workaround(one_thread=True)  # as pusupu bridge does, before any computation
    setup_jax(synchronous_cpu=True)
    from pusupu_jax.hw_bridge.canopen_link import CanLink, open_bus
    from pusupu_jax.hw_bridge.loop import BridgeLoop, bridge_reference, plan
    from pusupu_jax.hw_bridge.protocol import FEEDBACK
    from pusupu_jax.hw_bridge.runner import steal_seconds
    from pusupu_jax.hw_bridge.safety import Safety, limits_for
    from pusupu_jax.hw_bridge.session import Bridge, run_log as bridge_channels
    from pusupu_jax.hw_bridge.udp import Endpoint
    from pusupu_jax import __version__, gains, run_log
    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.params import LoopRates, ServoParams

    results = {
        "transport": args.transport,
        "seconds": args.seconds,
        "runs": args.runs,
        "watchdog_cycles": args.watchdog,
        "log": args.log,
        "cpus": os.cpu_count(),
        "uname": " ".join(os.uname()),
        "rates": {},
    }
    folder = Path(tempfile.mkdtemp())
    for rate in (float(r) for r in args.rates.split(",")):
        mode = "imc" if rate <= 1000 else "hybrid"
        path = gains.write(folder / f"{mode}.yaml", ServoParams.table1(), HybridGains(), LoopRates(), mode=mode)
        g = gains.load(path)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        url = f"udp://127.0.0.1:{port}" if args.transport == "udp" else "can://udp_multicast/239.74.163.9"
        robot_log = folder / f"robot_{rate:g}.log"
        with open(robot_log, "w") as err:
            robot = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "pusupu_jax.cli",
                    "sim-robot",
                    "--gains",
                    str(path),
                    "--listen",
                    url,
                    "--rate",
                    str(rate),
                ],
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
            )
        assert "listening" in robot.stdout.readline()
        loop = BridgeLoop(g, bridge_reference(g, "arc", plan(g, None, rate)[1]), rate=rate)
        runs = []
        try:
            for k in range(2 * args.runs if args.log == "alternate" else args.runs):
                # alternate: without, with, with, without, ... (ABBA): each way follows a run as often as it follows
                # a log's write, which holds the next run back for seconds
                logged = args.log == "on" or (args.log == "alternate" and k % 4 in (1, 2))
                after_write = bool(runs) and runs[-1]["log"]
                if args.transport == "udp":
                    ep = Endpoint(FEEDBACK, n_axes=len(loop.drive_modes), peer=("127.0.0.1", port))
                else:
                    ep = CanLink(open_bus(url), loop.drive_modes, np.asarray(g.servo.Kt * g.servo.I_max))
                probe = PauseProbe() if args.pause_probe else None
                steal = steal_seconds()
                started_ns = time.time_ns()
                run = Bridge(loop, ep, Safety(limits_for(g.servo), args.watchdog), hold_s=args.seconds).run(
                    args.seconds
                )
                stolen = steal_ms_since(steal)
                end = time.monotonic()
                ep.close()
                rep = run.report().as_dict()
                runs.append(
                    {
                        **{
                            k: rep[k]
                            for k in (
                                "cycles",
                                "missed_deadlines",
                                "missed_fraction",
                                "skipped_cycles",
                                "latency_us",
                                "feedback_age_us",
                                "record_us",
                                "completed",
                                "faults",
                                "realtime",
                            )
                        },
                        "steal_ms_per_cpu": stolen,
                        "log": logged,
                        "after_log_write": after_write,
                    }
                )
                if logged:
                    t0 = time.perf_counter()
                    meta = {"package_version": __version__, "source": "bench_bridge", "rate_hz": rate}
                    log = run_log.write(folder / "run.mcap", bridge_channels(run), meta, started_ns)
                    size = log.stat().st_size
                    runs[-1] |= {
                        "log_write_s": round(time.perf_counter() - t0, 4),
                        "log_bytes": size,
                        "log_bytes_per_s": round(size * rate / max(rep["cycles"], 1)),
                    }
                if probe is not None:
                    pauses = probe.stop()
                    runs[-1]["pauses"] = pauses
                    runs[-1]["pauses_in_last_s"] = [
                        (round(end - t, 4), ms)
                        for t, ms in pauses["all_cpus_stopped"]["spans"]
                        if end - 1.0 <= t <= end
                    ]
                print(json.dumps({"rate_hz": rate, **runs[-1]}), file=sys.stderr)
        finally:
            robot.terminate()
            robot.wait(30)

        stalls = [line.strip() for line in robot_log.read_text().splitlines() if ": stall " in line]
        for line in stalls:
            print(line, file=sys.stderr)
        results["rates"][f"{rate:g}"] = {
            "mode": mode,
            "drive_modes": [int(m) for m in loop.drive_modes],
            "runs": runs,
            "robot_stalls": stalls,
            "spread": {
                **percentile_spreads(runs, "latency_us", ("p50", "p99", "p99.9", "max")),
                **percentile_spreads(runs, "record_us", ("p50", "p99", "p99.9", "max")),
                "missed_fraction": spread([r["missed_fraction"] for r in runs]),
            },
        }
        if args.log == "alternate":  # the runs with the log written after them, against those without
            results["rates"][f"{rate:g}"]["by_log"] = {
                way: _group_figures([r for r in runs if r["log"] == logged])
                for way, logged in (("without", False), ("with", True))
            }
            # the same runs by what came before them: another run, or a log's write
            results["rates"][f"{rate:g}"]["by_previous"] = {
                way: _group_figures([r for r in runs if r["after_log_write"] == after])
                for way, after in (("after_a_run", False), ("after_a_log_write", True))
            }
    emit(results, args.out, indent=2)


def _group_figures(runs: list[dict]) -> dict:
    """One group's runs (with the log or without, after a run or after a log's write): their missed deadlines and
    cycles, and the spread of their missed fraction and latency."""
    return {
        "runs": len(runs),
        "missed_deadlines": [r["missed_deadlines"] for r in runs],
        "cycles": [r["cycles"] for r in runs],
        "missed_fraction": spread([r["missed_fraction"] for r in runs]),
        **percentile_spreads(runs, "latency_us", ("p50", "p99")),
    }


if __name__ == "__main__":
    main()
