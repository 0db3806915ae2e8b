"""The floor under the bridge's latency on this machine: a cycle that does less and less of the bridge's work (JSON).

The bridge's latency (``benchmarks/bench_bridge.py``) is the time from a cycle's wake-up to its command sent.
This benchmark runs the bridge's own :class:`pusupu_jax.hw_bridge.runner.CycleRunner`, with the same real-time settings,
on
cycles that do only part of that work, so that the part which is not ours (the interpreter, the clock, the kernel's
sockets, JAX's dispatch) can be read apart from the rest:

* ``empty``: the cycle returns at once (the runner's own bookkeeping and the clock);
* ``udp-raw``: one non-blocking ``recv`` until empty and one ``sendto`` of a prebuilt 130-byte datagram (the size
  of a six-axis command) to the echo process: the kernel's loopback and the interpreter, none of our code;
* ``udp``: the cycle polls a UDP :class:`pusupu_jax.hw_bridge.udp.Endpoint` (decoding what came, as the bridge does) and
  sends
  one command packet of the protocol for six axes to an echo process on the other CPU, which answers each with a
  feedback packet;
* ``udp+jit``: the same, plus one call of a jitted function that adds its input to its state (the dispatch of a
  compiled step that computes nothing, through :class:`pusupu_jax.hw_bridge.compiled.FlatStep` as the bridge calls its
  loops),
  with the bridge's warming: the runner's ``prepare`` calls it once before the deadline and drops the result;
* ``udp+loops``: the bridge's own calls of a run's cycle, in its order, on the echo's feedback: ``Endpoint.poll``,
  :meth:`pusupu_jax.hw_bridge.safety.Safety.check_feedback`, :meth:`pusupu_jax.hw_bridge.loop.BridgeLoop.step` (Table 1
  gains, IMC, the
  arc, every drive in CSV, warmed as the bridge warms it), :meth:`~pusupu_jax.hw_bridge.safety.Safety.limit_command` and
  the
  command sent; each part is timed too (``parts_us``).  What is left between this stage and the bridge's own
  latency is the session's bookkeeping and the simulated robot in place of the echo.

Then, for ``--pause-seconds``, the machine's own pauses with nothing else running (``timing.PauseProbe``: a
real-time process on each CPU sleeps 0.5 ms at a time and records every return more than 2 ms after the one
before; gaps that overlap on every CPU are the whole machine stopping at once, a hypervisor pause counted as
steal time or not).

Per stage: cycles, missed deadlines, busy-time percentiles (wake-up to return, us) and wake-up lateness.  The
stages alternate ``--rounds`` times, so that each sees the same load::

    python benchmarks/bench_rt_floor.py [--rate 1000] [--seconds 20] [--rounds 3] [--pause-seconds 60] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from timing import PauseProbe, emit, percentile_spreads, spread  # beside this script

ECHO = r"""
import os, sys, time
import numpy as np
from pusupu_jax.hw_bridge import protocol
from pusupu_jax.hw_bridge.udp import Endpoint
cpus = sorted(os.sched_getaffinity(0))
os.sched_setaffinity(0, {cpus[0]})
ep = Endpoint(protocol.COMMAND, n_axes=6)
print(ep.address[1], flush=True)
n, seq, end = 6, 0, time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    cmd = ep.poll(timeout=0.05)
    if cmd is None:
        continue
    seq += 1
    ep.send(protocol.encode_feedback(protocol.Feedback(seq, time.monotonic_ns(), cmd.sequence, np.zeros(n, np.uint16),
            np.zeros(n, np.int8), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(3))))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=1000.0, help="Hz")
    ap.add_argument("--seconds", type=float, default=20.0, help="per stage and round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--pause-seconds", type=float, default=60.0, help="the pause probe's length (0: not run)")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if not (args.rate > 0 and args.seconds > 0 and args.rounds >= 1 and args.pause_seconds >= 0):
        ap.error(
            f"expected a positive rate and seconds, at least one round and pause seconds >= 0, got {args.rate}, "
            f"{args.seconds}, {args.rounds}, {args.pause_seconds}"
        )

    from pusupu_jax.runtime import apply_xla_workaround, setup_jax

    apply_xla_workaround(one_thread=True)  # as pusupu bridge has it
    setup_jax(synchronous_cpu=True)
    import jax.numpy as jnp

    from pusupu_jax.hw_bridge import protocol
    from pusupu_jax.hw_bridge.compiled import FlatStep
    from pusupu_jax.hw_bridge.loop import BridgeLoop, bridge_reference
    from pusupu_jax.hw_bridge.runner import CycleRunner, percentiles, realtime_setup
    from pusupu_jax.hw_bridge.safety import Safety, limits_for
    from pusupu_jax.hw_bridge.udp import Endpoint
    from pusupu_jax import gains
    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.params import LoopRates, ServoParams

    n = 6
    with tempfile.TemporaryDirectory() as folder:
        g = gains.load(
            gains.write(Path(folder) / "imc.yaml", ServoParams.table1(), HybridGains(), LoopRates(), mode="imc")
        )
    loop = BridgeLoop(g, bridge_reference(g, "arc"))
    safety = Safety(limits_for(g.servo), 1)
    loop.start(np.zeros(n), np.zeros(n))
    step = FlatStep(lambda s, u: (s + u, s), (), jnp.zeros(n), (np.zeros(n),))
    state = [step.state]
    seq = [0]
    zeros = (np.zeros(n, np.uint16), np.full(n, 9, np.int8))

    raw = []  # the udp-raw stage's datagrams, encoded before each of its runs (the echo drops replayed sequences)

    def io_raw(k, skipped):
        try:
            while ep.sock.recv(protocol.MAX_PACKET + 1):
                pass
        except BlockingIOError:
            pass
        ep.sock.sendto(raw[k], ep.peer)
        return True

    def io(k, skipped):
        ep.poll()
        seq[0] += 1
        ep.send_command(protocol.Command(seq[0], 0, 0, *zeros, np.zeros(n)))
        return True

    def io_jit(k, skipped):
        fb = ep.poll()
        state[0], out = step(state[0], np.zeros(n) if fb is None else fb.velocity)
        seq[0] += 1
        ep.send_command(protocol.Command(seq[0], 0, 0, *zeros, out))
        return True

    def warm(k):
        step(state[0], np.zeros(n))

    cycles = int(args.rate * args.seconds)
    parts = np.zeros((cycles, 5))  # the udp+loops stage's parts of each cycle [s]
    enabled = np.full(n, 0x0F, np.uint16)  # controlword: enable operation

    def io_loops(k, skipped):
        t0 = time.perf_counter()
        fb = ep.poll()
        t1 = time.perf_counter()
        theta, omega = (fb.position, fb.velocity) if fb is not None else (np.zeros(n), np.zeros(n))
        if fb is not None:
            safety.check_feedback(k, 0, fb.position, fb.velocity, fb.torque)
        t2 = time.perf_counter()
        out = loop.step(k % loop.cycles, theta, omega)
        t3 = time.perf_counter()
        target = safety.limit_command(k, loop.drive_modes, out)
        t4 = time.perf_counter()
        seq[0] += 1
        ep.send_command(protocol.Command(seq[0], time.monotonic_ns(), 0, enabled, loop.drive_modes, target))
        parts[k] = (t1 - t0, t2 - t1, t3 - t2, t4 - t3, time.perf_counter() - t4)
        return True

    stages = {
        "empty": (lambda k, skipped: True, None),
        "udp-raw": (io_raw, None),
        "udp": (io, None),
        "udp+jit": (io_jit, warm),
        "udp+loops": (io_loops, lambda k: loop.warm(k % loop.cycles)),
    }
    part_names = ("poll", "check_feedback", "step", "limit_command", "send")
    total = len(stages) * args.rounds * args.seconds + 30  # s: the echo's own limit, past every stage
    echo = subprocess.Popen([sys.executable, "-c", ECHO, str(total)], stdout=subprocess.PIPE, text=True)
    ep = Endpoint(protocol.FEEDBACK, n_axes=n, peer=("127.0.0.1", int(echo.stdout.readline())))
    rt = realtime_setup()
    runner = CycleRunner(args.rate)
    runs = {name: [] for name in stages}
    try:
        for r in range(args.rounds):
            for name, (fn, prepare) in stages.items():
                if name == "udp-raw":
                    raw[:] = [
                        protocol.encode_command(protocol.Command(seq[0] + 1 + k, 0, 0, *zeros, np.zeros(n)))
                        for k in range(cycles)
                    ]
                    seq[0] += cycles
                parts[:] = np.nan  # cycles skipped on overrun time nothing
                st = runner.run(fn, cycles, prepare)
                runs[name].append(
                    {
                        "cycles": st.cycles,
                        "missed_deadlines": st.missed,
                        "missed_fraction": st.missed / max(cycles, 1),
                        "busy_us": percentiles(1e6 * st.busy),
                        "wake_late_us": percentiles(1e6 * st.wake_late),
                    }
                )
                if name == "udp+loops":
                    timed = parts[~np.isnan(parts[:, 0])]
                    runs[name][-1]["parts_us"] = {p: percentiles(1e6 * timed[:, j]) for j, p in enumerate(part_names)}
                print(json.dumps({"stage": name, "round": r + 1, **runs[name][-1]}), file=sys.stderr, flush=True)
    finally:
        rt.restore()
        echo.terminate()
        echo.wait(30)
        ep.close()

    result = {
        "benchmark": "rt_floor",
        "rate_hz": args.rate,
        "seconds": args.seconds,
        "rounds": args.rounds,
        "cpus": os.cpu_count(),
        "uname": " ".join(os.uname()),
        "realtime": rt.settings,
        "runs": runs,
        "spread": {
            name: {
                **percentile_spreads(v, "busy_us", ("p50", "p99", "p99.9")),
                **percentile_spreads(v, "wake_late_us", ("p99",)),
                "missed_fraction": spread([x["missed_fraction"] for x in v]),
            }
            for name, v in runs.items()
        },
    }
    result["spread"]["udp+loops"]["parts_us"] = {
        p: {q: spread([r["parts_us"][p][q] for r in runs["udp+loops"]]) for q in ("p50", "p99")} for p in part_names
    }
    if args.pause_seconds:
        probe = PauseProbe()
        time.sleep(args.pause_seconds)
        result["pauses"] = probe.stop()
    emit(result, args.out)


if __name__ == "__main__":
    main()
