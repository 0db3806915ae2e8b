"""The floor under the bridge's latency on this machine: a cycle that does less and less of the bridge's work (JSON).

The bridge's latency (``benchmarks/bench_bridge.py``) is the time from a cycle's wake-up to its command sent.
This benchmark runs the bridge's own :class:`hw_bridge.runner.CycleRunner`, with the same real-time settings, on
cycles that do only part of that work, so that the part which is not ours (the interpreter, the clock, the kernel's
sockets, JAX's dispatch) can be read apart from the rest:

* ``empty``: the cycle returns at once (the runner's own bookkeeping and the clock);
* ``udp-raw``: one non-blocking ``recv`` until empty and one ``sendto`` of a prebuilt 130-byte datagram (the size
  of a six-axis command) to the echo process: the kernel's loopback and the interpreter, none of our code;
* ``udp``: the cycle polls a UDP :class:`hw_bridge.udp.Endpoint` (decoding what came, as the bridge does) and sends
  one command packet of the protocol for six axes to an echo process on the other CPU, which answers each with a
  feedback packet;
* ``udp+jit``: the same, plus one call of a jitted function that adds its input to its state (the dispatch of a
  compiled step that computes nothing, through :class:`hw_bridge.compiled.FlatStep` as the bridge calls its loops),
  with the bridge's warming: the runner's ``prepare`` calls it once before the deadline and drops the result.

Per stage: cycles, missed deadlines, busy-time percentiles (wake-up to return, us) and wake-up lateness.  The
stages alternate ``--rounds`` times, so that each sees the same load::

    python benchmarks/bench_rt_floor.py [--rate 1000] [--seconds 20] [--rounds 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from timing import emit, percentile_spreads, spread  # beside this script

ECHO = r"""
import os, sys, time
import numpy as np
from hw_bridge import protocol
from hw_bridge.udp import Endpoint
cpus = sorted(os.sched_getaffinity(0))
os.sched_setaffinity(0, {cpus[0]})
ep = Endpoint(protocol.COMMAND)
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
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if not (args.rate > 0 and args.seconds > 0 and args.rounds >= 1):
        ap.error(f"expected a positive rate and seconds and at least one round, got {args.rate}, {args.seconds}, "
                 f"{args.rounds}")

    from pusupu_jax.config import setup_jax

    setup_jax()
    import jax.numpy as jnp

    from hw_bridge import protocol
    from hw_bridge.compiled import FlatStep
    from hw_bridge.runner import CycleRunner, percentiles, realtime_setup
    from hw_bridge.udp import Endpoint

    n = 6
    total = 4 * args.rounds * args.seconds + 30
    echo = subprocess.Popen([sys.executable, "-c", ECHO, str(total)], stdout=subprocess.PIPE, text=True)
    port = int(echo.stdout.readline())
    ep = Endpoint(protocol.FEEDBACK, peer=("127.0.0.1", port))
    step = FlatStep(lambda s, u: (s + u, s), (), jnp.zeros(n), (np.zeros(n),))
    state = [step.state]
    seq = [0]
    zeros = (np.zeros(n, np.uint16), np.full(n, 9, np.int8))

    raw = []  # the udp-raw stage's datagrams, encoded before each of its runs (the echo drops replayed sequences)
    peer = ("127.0.0.1", port)

    def io_raw(k, skipped):
        try:
            while ep.sock.recv(protocol.MAX_PACKET + 1):
                pass
        except BlockingIOError:
            pass
        ep.sock.sendto(raw[k], peer)
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

    stages = {"empty": (lambda k, skipped: True, None), "udp-raw": (io_raw, None), "udp": (io, None),
              "udp+jit": (io_jit, warm)}
    rt = realtime_setup()
    runner = CycleRunner(args.rate)
    cycles = int(args.rate * args.seconds)
    runs = {name: [] for name in stages}
    try:
        for r in range(args.rounds):
            for name, (fn, prepare) in stages.items():
                if name == "udp-raw":
                    raw[:] = [protocol.encode_command(protocol.Command(seq[0] + 1 + k, 0, 0, *zeros, np.zeros(n)))
                              for k in range(cycles)]
                    seq[0] += cycles
                st = runner.run(fn, cycles, prepare)
                runs[name].append({"cycles": st.cycles, "missed_deadlines": st.missed,
                                   "missed_fraction": st.missed / max(cycles, 1),
                                   "busy_us": percentiles(1e6 * st.busy), "wake_late_us": percentiles(1e6 * st.wake_late)})
                print(json.dumps({"stage": name, "round": r + 1, **runs[name][-1]}), file=sys.stderr, flush=True)
    finally:
        rt.restore()
        echo.terminate()
        echo.wait(30)
        ep.close()

    result = {"benchmark": "rt_floor", "rate_hz": args.rate, "seconds": args.seconds, "rounds": args.rounds,
              "cpus": os.cpu_count(), "uname": " ".join(os.uname()), "realtime": rt.settings, "runs": runs,
              "spread": {name: {**percentile_spreads(v, "busy_us", ("p50", "p99", "p99.9")),
                                **percentile_spreads(v, "wake_late_us", ("p99",)),
                                "missed_fraction": spread([x["missed_fraction"] for x in v])}
                         for name, v in runs.items()}}
    emit(result, args.out)


if __name__ == "__main__":
    main()
