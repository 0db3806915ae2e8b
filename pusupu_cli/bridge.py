"""``pusupu bridge`` and ``pusupu sim-robot``: the tuned loops against drives, and a simulated robot to run them on."""

from __future__ import annotations

import json
import socket
import sys
import time
from typing import TYPE_CHECKING

from pusupu_jax.params import ParameterError

from .common import check_along_paths, check_log_path, check_plot_path, machine_of

if TYPE_CHECKING:
    from pusupu_jax.hw_bridge.session import BridgeReport


def add_parsers(sub) -> None:
    b = sub.add_parser("bridge", help="run a gain file's loops at real-time rate against the drives of a robot")
    b.add_argument(
        "--gains",
        metavar="FILE",
        required=True,
        help="a gain file (pusupu tune's gains.yaml); a bad or unstable one is refused before anything is sent",
    )
    b.add_argument(
        "--robot",
        metavar="URL",
        required=True,
        help="udp://HOST:PORT of a robot controller, or can://INTERFACE/CHANNEL of a CANopen bus with CiA "
        "402 drives at node IDs 1-6 (python-can interfaces) (pusupu sim-robot for a simulated one)",
    )
    b.add_argument(
        "--rate",
        type=float,
        metavar="HZ",
        help="cycle rate, 1 to 4000 (default: the gain file's rate "
        "of the fastest loop the bridge closes: 1000 in CSV, "
        "4000 with CST axes)",
    )
    b.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help="seconds of the path (default all of it; at most what half of the memory holds of the run's record)",
    )
    b.add_argument(
        "--trajectory",
        metavar="NAME|FILE",
        default="arc",
        help="arc, p2p, circle, tilt, excite or a path file: waypoints (.yaml, .yml) or a pose table (.csv) "
        "(docs/paths.md); checked against the machine before anything is sent (default arc)",
    )
    b.add_argument(
        "--allow-other-machine",
        action="store_true",
        help="run a gain file tuned on another machine than --machine's (refused by default)",
    )
    b.add_argument(
        "--drive-modes",
        metavar="M[,M...]",
        default="csv",
        help="csv or cst, one for all axes or six comma-separated; hybrid mode always runs branch 6 in "
        "cst (default csv)",
    )
    b.add_argument(
        "--watchdog",
        type=int,
        default=5,
        metavar="N",
        help="cycles without fresh feedback before a safe stop (default 5)",
    )
    b.add_argument(
        "--bind",
        metavar="HOST",
        default="127.0.0.1",
        help="local address (default loopback; another is said on stderr)",
    )
    b.add_argument("--no-realtime", action="store_true", help="do not ask for SCHED_FIFO, mlockall or CPU affinity")
    b.add_argument(
        "--lockstep",
        type=float,
        default=0.0,
        metavar="S",
        help="each cycle waits up to S seconds for the answer to the last command, and a late cycle moves the "
        "deadlines after it instead of skipping: for runs against the simulated robot on a shared machine, whose "
        "results must not depend on scheduling; never against drives (default 0: real time)",
    )
    b.add_argument("--json", action="store_true", help="print the report as JSON")
    b.add_argument("--plot", metavar="FIG", help="write the latency histogram and the tracking trace")
    b.add_argument(
        "--log",
        metavar="MCAP",
        help="write the run as an MCAP log after it (commands, feedback, faults; Foxglove, PlotJuggler; docs/logs.md)",
    )
    r = sub.add_parser("sim-robot", help="a simulated robot behind the bridge's protocol: the machine and its drives")
    r.add_argument("--gains", metavar="FILE", required=True, help="the gain file of the drives' inner loops")
    r.add_argument(
        "--listen",
        metavar="URL",
        default="udp://127.0.0.1:5600",
        help="udp://HOST:PORT or can://INTERFACE/CHANNEL (python-can, e.g. can://udp_multicast/239.74.163.2 "
        "or can://socketcan/can0) (default udp://127.0.0.1:5600)",
    )
    r.add_argument("--rate", type=float, metavar="HZ", help="the bridge's --rate (default the gain file's)")
    r.add_argument(
        "--drive-modes",
        metavar="M[,M...]",
        default="csv",
        help="the bridge's --drive-modes: with --rate, they say which loop the rate is of (default csv)",
    )
    r.add_argument("--kin-error", type=int, metavar="SEED", help="seeded kinematic errors of the machine (0.5 mm std)")
    r.add_argument(
        "--noise-seed",
        type=int,
        default=0,
        metavar="SEED",
        help="the seed of the sensors' noise, where the machine file gives current_noise or encoder_counts (the "
        "current noise's draws and the encoders' phases; default 0)",
    )
    r.add_argument(
        "--fine-steps",
        type=int,
        metavar="N",
        help="step the machine N times per current-loop tick, each tick on the latest speed: a truth finer than the "
        "model that tune and identify step, one step per velocity period (default: that model's stepping)",
    )
    for sp in (b, r):
        sp.add_argument(
            "--machine", metavar="FILE", help="the machine file (pusupu machine init; default: the built-in machine)"
        )
    r.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND@S[:ARG]",
        help="a fault for the next session (repeat for later sessions): stop, delay, drop, reorder, "
        "corrupt, nan, range, garbage or none, S seconds after enable (sim_robot/robot.py)",
    )
    r.add_argument("--seconds", type=float, metavar="S", help="serve for S seconds, then exit (default: until ^C)")
    r.add_argument(
        "--drive-watchdog",
        type=float,
        default=0.05,
        metavar="S",
        help="the drives' sync watchdog: enabled and no command for S seconds, they fault and brake (default 0.05)",
    )
    r.add_argument(
        "--no-realtime",
        action="store_true",
        help="do not ask for SCHED_FIFO, mlockall or CPU affinity (default: ask, on the first CPU, "
        "leaving the last to the bridge)",
    )


def _robot_url(url: str):
    """(host, port) of udp://HOST:PORT, or None for can://INTERFACE/CHANNEL."""
    from pusupu_jax.hw_bridge.udp import parse_url

    if url.startswith("can://"):
        interface, _, channel = url[len("can://") :].partition("/")
        if not interface or not channel:
            raise ParameterError(f"--robot: expected can://INTERFACE/CHANNEL, got {url!r}")
        return None
    try:
        host, port = parse_url(url)
    except ValueError as e:
        raise ParameterError(f"--robot: {e}") from None
    if port == 0:  # a port to send to: 0 binds anywhere but reaches no one
        raise ParameterError(f"--robot: expected udp://HOST:PORT with a port from 1 to 65535, got {url!r}")
    try:  # the bridge's socket is IPv4
        socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    except OSError as e:
        raise ParameterError(f"--robot: expected a host with an IPv4 address, got {host!r} ({e.strerror})") from None
    return host, port


def _warn_beyond_loopback(option: str, value: str, host: str, what: str) -> None:
    """One line on stderr when ``host`` (of ``option``'s ``value``) is not a loopback address: ``what`` then takes
    packets from the network."""
    from pusupu_jax.hw_bridge.udp import beyond_loopback

    try:
        where = beyond_loopback(host)
    except OSError as e:
        raise ParameterError(
            f"{option}: expected a host that resolves to an IPv4 address, got {host!r} ({e.strerror or e})"
        ) from None
    if where is not None:
        print(f"pusupu: warning: {option} {value}: {what} on {where}, not on loopback alone", file=sys.stderr)


def _drive_modes(text: str, n: int = 6):
    names = text.split(",")
    if len(names) == 1:
        names = names * n
    if len(names) != n or not set(names) <= {"csv", "cst"}:
        raise ParameterError(f"--drive-modes: expected csv or cst, once or {n} times, got {text!r}")
    return names


def run_bridge(args) -> int:
    import math

    import numpy as np

    from pusupu_jax import gains
    from pusupu_jax.runtime import apply_xla_workaround, setup_jax

    apply_xla_workaround(one_thread=True)  # before any computation: the gain file's checks run on JAX
    # before any computation too: JAX's CPU backend starts with the first one and reads then whether to dispatch
    # synchronously (the cycle's thread runs its steps itself: hw_bridge.compiled.cpu), and the gain file's checks
    # compile programs that the cache keeps for the next run
    setup_jax(synchronous_cpu=True)

    address = _robot_url(args.robot)
    if address is not None:
        _warn_beyond_loopback("--bind", args.bind, args.bind, "the bridge takes packets")
    modes = _drive_modes(args.drive_modes)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ParameterError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if not args.watchdog >= 1:
        raise ParameterError(f"--watchdog: expected at least 1 cycle, got {args.watchdog}")
    if not 0.0 <= args.lockstep <= 10.0:
        raise ParameterError(f"--lockstep: expected seconds in [0, 10], got {args.lockstep}")
    if args.plot is not None:
        check_plot_path(args.plot)
    if args.log is not None:
        check_log_path(args.log)
    from pusupu_jax import machine_file

    machine = machine_of(args)
    g = gains.load(args.gains, machine=machine)  # refused here (one line, exit 2) before any socket opens
    if not g.tuned_on(machine):
        message = (
            f"--gains {args.gains}: tuned on machine {g.machine['name']!r} (digest {g.machine['digest'][:12]}),"
            f" not on {machine.name!r} (digest {machine_file.digest(machine)[:12]})"
        )
        if not args.allow_other_machine:
            raise ParameterError(f"{message}; give that machine's file with --machine, or --allow-other-machine")
        print(f"pusupu: warning: {message}; running it as --allow-other-machine asks", file=sys.stderr)
    # the gain check of load() takes the load at home; the path to run may carry the sliders lighter or heavier
    check_along_paths(g, machine, [args.trajectory], gains.FLOORS, f"--gains {args.gains}")
    from pusupu_jax.hw_bridge.loop import BridgeLoop, bridge_reference, cycle_rate, plan
    from pusupu_jax.hw_bridge.protocol import CST, FEEDBACK
    from pusupu_jax.hw_bridge.safety import Safety, limits_for
    from pusupu_jax.hw_bridge.session import RECORD_BYTES, Bridge, End, longest_run, record_memory
    from pusupu_jax.hw_bridge.udp import Endpoint

    modes = modes if args.drive_modes != "csv" else None
    try:
        codes, rates = plan(g, modes, args.rate)
    except ValueError as e:
        raise ParameterError(str(e)) from None
    rate = cycle_rate(rates, bool((codes == CST).any()))
    if args.duration is not None and args.duration > longest_run(rate):
        raise ParameterError(
            f"--duration: expected at most {longest_run(rate):.6g} s at {rate:g} Hz (a run's record "
            f"takes up to {RECORD_BYTES} bytes a cycle, in half of this machine's memory, "
            f"{record_memory() / 2**30:.3g} GiB), got {args.duration:g}"
        )
    try:
        loop = BridgeLoop(g, bridge_reference(g, args.trajectory, rates, machine), modes, args.rate)
    except ValueError as e:
        raise ParameterError(str(e)) from None
    if address is None:
        from pusupu_jax.hw_bridge.canopen_link import CanLink, open_bus

        try:
            endpoint = CanLink(open_bus(args.robot), loop.drive_modes, np.asarray(g.servo.Kt * g.servo.I_max))
        except Exception as e:  # no drive answers the SDO set-up, a bus that does not open
            raise ParameterError(f"--robot {args.robot}: CANopen set-up failed: {e}") from None
    else:
        endpoint = Endpoint(FEEDBACK, n_axes=len(loop.drive_modes), bind=(args.bind, 0), peer=address)
    print(
        f"bridge: {g.mode} loops at {loop.rate:g} Hz (position every {loop.n_position} cycle(s)), drives "
        f"{','.join('cst' if m == CST else 'csv' for m in loop.drive_modes)}, robot {args.robot}",
        file=sys.stderr,
    )
    started_ns = time.time_ns()
    try:
        safety = Safety(limits_for(g.servo, machine.geometry), args.watchdog)
        run = Bridge(loop, endpoint, safety, lockstep_s=args.lockstep).run(args.duration, not args.no_realtime)
    finally:
        endpoint.close()
    report = run.report(screw=loop.drive.screw)
    if args.log:  # after the run, from its record: nothing is written inside a cycle
        from pusupu_jax import __version__, run_log
        from pusupu_jax.hw_bridge.session import run_log as bridge_channels

        metadata = {
            "package_version": __version__,
            "source": "pusupu bridge",
            "mode": str(g.mode),
            "gain_file_checksum": g.document["checksum"],
            "machine": machine_file.reference(machine),
            "trajectory": args.trajectory,
            "robot": args.robot,
            "rate_hz": loop.rate,
            "ended": str(run.ended),
        }
        run_log.write(args.log, bridge_channels(run), metadata, started_ns)
    if args.json:
        print(json.dumps(report.as_dict(), indent=2))
    else:
        print(_table(report))
    if args.plot:
        bridge_figure(run, report, args.plot)
    for line in report.faults:
        print(f"pusupu: fault: {line}", file=sys.stderr)
    if run.ended in (End.SIGINT, End.SIGTERM):
        print(f"pusupu: {run.ended}: the run stopped (quick stop, then disable voltage)", file=sys.stderr)
    # 1: a safe stop on a fault, the bridge's own errors included; 128 + the signal's number: the run stopped on it
    return {End.COMPLETED: 0, End.FAULT: 1, End.SIGINT: 130, End.SIGTERM: 143}[run.ended]


def _table(rep: BridgeReport) -> str:
    from pusupu_jax.hw_bridge.session import End

    lines = [
        f"cycles {rep.cycles} at {rep.rate_hz:g} Hz, missed deadlines {rep.missed_deadlines} "
        f"({100 * rep.missed_fraction:.3f} %), skipped {rep.skipped_cycles}"
    ]
    for key, p in (
        ("latency_us", rep.latency_us),
        ("feedback_age_us", rep.feedback_age_us),
        ("record_us", rep.record_us),
    ):
        if p:
            lines.append(
                f"{key:15s} p50 {p['p50']:8.1f}  p99 {p['p99']:8.1f}  p99.9 {p['p99.9']:8.1f}  max {p['max']:8.1f}"
            )
    if rep.rms_tracking_error_mm is not None:
        lines.append(
            f"platform tracking error: RMS {rep.rms_tracking_error_mm:.4f} mm, max {rep.max_tracking_error_mm:.4f} mm"
        )
    lines.append(f"rejected packets: {rep.rejected_packets or 'none'}")
    lines += [f"real-time {line}" for line in rep.realtime]
    lines.append(
        {End.COMPLETED: "completed", End.FAULT: f"stopped: {len(rep.faults)} fault(s)"}.get(
            rep.ended, f"stopped: {rep.ended}"
        )
    )
    return "\n".join(lines)


def bridge_figure(run, report: BridgeReport, path) -> None:
    """The latency histogram [us] and the tracking trace (branch 1's reference and position, every branch's error)."""
    import numpy as np

    import matplotlib.pyplot as plt

    from pusupu_jax.plots import save_atomic  # the command selected the Agg backend (cli.main)

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    lat = np.asarray(run.latency_us)
    if len(lat):
        a.hist(lat, bins=100, log=True)
        for key in ("p50", "p99", "p99.9"):
            a.axvline(report.latency_us[key], ls="--", color="k", lw=0.8)
    a.set_xlabel("wake-up to command sent [us]")
    a.set_ylabel("cycles")
    a.set_title(f"{report.cycles} cycles at {report.rate_hz:g} Hz, {report.missed_deadlines} missed")
    if run.position:
        t = np.asarray(run.t)
        e = (np.asarray(run.position) - np.asarray(run.reference)) * 1e3
        b.plot(t, e, lw=0.8)
        b.set_ylabel("branch error [mrad of motor angle]")
        b.legend([f"branch {k + 1}" for k in range(e.shape[1])], fontsize=7)
    b.set_xlabel("t [s]")
    b.set_title("tracking")
    save_atomic(fig, path)


def run_sim_robot(args) -> int:
    import math

    from pusupu_jax import gains
    from pusupu_jax.runtime import apply_xla_workaround, setup_jax

    apply_xla_workaround(one_thread=True)  # before any computation: the gain file's checks run on JAX
    setup_jax(synchronous_cpu=True)  # before any computation, as the bridge's (run_bridge says why)

    from pusupu_jax.hw_bridge.udp import parse_url

    if not args.listen.startswith("can://"):
        try:
            host, _ = parse_url(args.listen)
        except ValueError as e:
            raise ParameterError(f"--listen: {e}") from None
        _warn_beyond_loopback("--listen", args.listen, host, "the simulated robot takes commands")
    if not 0.0 < args.drive_watchdog <= 60.0:
        raise ParameterError(f"--drive-watchdog: expected seconds in (0, 60], got {args.drive_watchdog}")
    if args.kin_error is not None and args.kin_error < 0:
        raise ParameterError(f"--kin-error: expected a non-negative integer seed, got {args.kin_error}")
    if args.noise_seed < 0:
        raise ParameterError(f"--noise-seed: expected a non-negative integer seed, got {args.noise_seed}")
    if args.fine_steps is not None and not 1 <= args.fine_steps <= 64:
        raise ParameterError(f"--fine-steps: expected a whole number of steps from 1 to 64, got {args.fine_steps}")
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise ParameterError(f"--seconds: expected a positive number of seconds, got {args.seconds}")
    from pusupu_jax.sim_robot.robot import FaultSpec, RobotModel, main_loop

    try:
        faults = [FaultSpec.parse(f) for f in args.fault]
    except ValueError as e:
        raise ParameterError(str(e)) from None
    machine = machine_of(args)
    g = gains.load(args.gains, machine=machine)
    from pusupu_jax.hw_bridge.loop import plan
    from pusupu_jax.hw_bridge.protocol import CST

    try:
        codes, _ = plan(g, None if args.drive_modes == "csv" else _drive_modes(args.drive_modes), args.rate)
    except ValueError as e:
        raise ParameterError(str(e)) from None
    model = RobotModel(
        g,
        args.rate,
        args.kin_error,
        cst=bool((codes == CST).any()),
        machine=machine,
        noise_seed=args.noise_seed,
        fine_steps=args.fine_steps,
    )
    return main_loop(model, args.listen, faults, args.seconds, args.drive_watchdog, not args.no_realtime)
