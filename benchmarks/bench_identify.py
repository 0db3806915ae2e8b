"""Does ``pusupu identify`` recover a machine it did not start from?  Per fitted value: truth, fit, standard error
(JSON on stdout).

A "true" machine (``docs/examples/machine_as_built.yaml``) differs from the built-in one in every value the fit is
asked for: per axis Coulomb and viscous friction, rotor inertia and torque constant (its back-EMF constant with it),
and a 5 kg payload off centre.
``pusupu sim --plant mjx --log`` runs Table 1's gains (IMC) on it along ``--trajectory``; ``pusupu identify``'s fit
(:func:`pusupu_jax.machine_fit.fit`) then starts from the built-in machine with a 3 kg payload at the platform
centre (the payload's inertia given as the truth's, as from CAD: it is not fitted) and fits ``--fit``.  A payload
centre of mass that is not fitted is a model error unless ``--true-com 0,0,0``.

``--realtime LOAD`` runs that bridge in real time instead, beside LOAD busy processes, so that cycles go late, are
skipped, and meet a robot that took only the newer of two commands: the log's timing says how each went, and
``--timing with,without`` fits it with identify's replay of that timing and with one that assumes a command a row.

With ``--source sim`` (default) the log is written by the same MJX model that replays it, at the same step: this
measures the fit and what the data excite, not the model's error.  With ``--source bridge`` the true machine is the
simulated robot (``pusupu sim-robot --machine true.yaml``: C MuJoCo, with the drives' loops in the robot) and the log
is ``pusupu bridge --log``'s over UDP on loopback, in lock step (``--lockstep``: each cycle waits for the robot's
answer, so no cycle is skipped on a loaded machine); ``--fine-steps N`` has the simulated robot step its machine N
times per current-loop tick (``pusupu sim-robot --fine-steps``), a truth finer than the fitting model.
``--robot-sensors BITS,AMPS`` gives the simulated robot sensors of its own (encoders of BITS a turn, current noise of
AMPS), which its drives' loops close on as a robot's do.
``--noise-seeds N`` fits N more copies of the log with the sensors' noise drawn afresh: each motor angle rounded to
an encoder of ``--encoder-bits`` a turn (at a phase drawn per seed), and each current with Gaussian noise of
``--current-noise`` of its axis's RMS.  With ``--seeds-in-loop`` (and ``--source bridge``) each seed is a bridge run
of its own instead, the noise drawn inside the loop: the simulated robot gets those sensors (the current noise of
each axis from the noise-free run's RMS) and ``--noise-seed`` K, so its drives close their loops on what its
encoders (at phases drawn from K) and current sensors read, and the log holds what they reported.
``--known-encoders`` gives the start machine the robot's encoders (``encoder_counts``, as a user's machine file
would): identify's replay then takes the drives' speed from the counts, as the robot's drives do.
Each entry says whether the truth lies inside the value's 95 % interval
(1.96 standard errors), and ``coverage`` gives per solver and value the share of seeds whose interval covers it.
The later fits find the programs compiled (the logged data are their arguments).  ``--first-seed K --noisy-only``
fits seeds K, K+1, ... alone, so that several processes can share the seeds; ``--merge A.json B.json ...`` makes one
result of theirs.

``--step-check S`` runs identify's step check (:func:`pusupu_jax.machine_fit.fit`): the fitted values replayed at the
finer step S and moved by one Gauss-Newton step on that replay's residual; each entry gives the move
(``step_correction``) and each fit the finer replay's residual RMS before and after it (``step_check_rms``).

``--derivatives exact,finite-differences,mujoco-minimize`` fits each log once with each solver and Jacobian
(:class:`pusupu_jax.machine_fit.Derivatives`): the exact one through the replay, and the derivative-free anchors,
scipy's 2-point differences of the same residual with the same solver, bounds and tolerances, and MuJoCo's
``mujoco.minimize.least_squares`` on its own forward differences (each Jacobian's replays as one batch).  Each fit
gives the seconds spent in the residual's and the Jacobian's calls (``solve_s``, compiles left out), its cost in
forward replays (``replays``: every residual call, the differences' included, plus the Jacobian's seconds over one
residual call's) and ``trace``, the least residual RMS met against those seconds; ``anchor`` compares them per log,
and the seconds each took to the same residual (the higher of the two fits' least, to a millionth of it)::

    python benchmarks/bench_identify.py [--source sim|bridge] [--fine-steps N] [--robot-sensors BITS,AMPS]
        [--realtime LOAD] [--timing with[,without]]
        [--trajectory p2p] [--window 2]
        [--mech-step S] [--step-check S]
        [--fit friction,motor,payload] [--noise-seeds 0] [--first-seed 0] [--noisy-only] [--seeds-in-loop]
        [--known-encoders]
        [--derivatives exact[,finite-differences,...]] [--out FILE]
    python benchmarks/bench_identify.py --merge A.json B.json ... [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pusupu_jax  # noqa: F401, I001  before numpy: its one OpenBLAS thread, as pusupu identify has it
import numpy as np

from timing import emit, processor  # beside this script

# per axis Coulomb 28, 24, 20, 16, 30, 22 N and viscous friction 35, 60, 50, 80, 40, 55 N s/m (built-in 20 and 50),
# rotor inertia 2.26, 1.70, 2.07, 1.88, 2.44, 1.60 x 1e-4 kg m^2 (1.88), torque and back-EMF constants 1.19, 1.45,
# 1.322, 1.26, 1.40, 1.22 N m/A (1.322); a 5 kg payload at (0.03, -0.02, 0.05) m, inertia (0.02, 0.02, 0.03) kg m^2
EXAMPLES = Path(__file__).resolve().parent.parent / "docs" / "examples"
TRUE_MACHINE = EXAMPLES / "machine_as_built.yaml"
START_MACHINE = EXAMPLES / "machine_as_designed.yaml"  # the built-in one with a 3 kg payload at the centre


def _machines(tmp: Path, com: tuple[float, ...], sensors: tuple[int, float] | None = None):
    """The true machine (:data:`TRUE_MACHINE`, its payload's centre of mass at ``com`` [m], and where given its
    ``sensors``: encoders of that many bits a turn and current sensors of that standard deviation [A], on every axis)
    and the start machine (:data:`START_MACHINE`), written as machine files; the true one returned."""
    from pusupu_jax import machine_file
    from pusupu_jax.files import write_atomic

    given = machine_file.load(TRUE_MACHINE)
    truth = dataclasses.replace(given, name="true", payload=dataclasses.replace(given.payload, com=com))
    if sensors is not None:
        truth = _sensed(truth, *sensors)
    start = dataclasses.replace(machine_file.load(START_MACHINE), name="start")
    for name, m in (("true", truth), ("start", start)):
        write_atomic(tmp / f"{name}.yaml", machine_file.template(m))
    return truth


def _sensed(machine, bits: int, amps):
    """``machine`` with encoders of ``bits`` a turn and current sensors of standard deviation ``amps`` [A] (one for
    every axis, or one per axis)."""
    return dataclasses.replace(
        machine, encoder_counts=np.full(6, 2**bits), current_noise=np.broadcast_to(np.asarray(amps, float), (6,)).copy()
    )


def _sim_log(tmp: Path, gain_path: Path, trajectory: str) -> None:
    """``pusupu sim --plant mjx --log``: the true machine's run, by the fitting model itself."""
    subprocess.run(
        [sys.executable, "-m", "pusupu_jax.cli", "sim", "--plant", "mjx", "--machine", str(tmp / "true.yaml")]
        + ["--gains", str(gain_path), "--trajectory", trajectory, "--log", str(tmp / "true.mcap")],
        check=True,
        stdout=subprocess.DEVNULL,
        env=os.environ,
    )


def _bridge_log(
    tmp: Path,
    gain_path: Path,
    trajectory: str,
    seconds: float,
    fine_steps: int | None,
    robot: str = "true",
    seed=None,
    load: int | None = None,
) -> dict:
    """``pusupu bridge --log ROBOT.mcap`` against ``pusupu sim-robot --machine ROBOT.yaml [--fine-steps fine_steps]
    [--noise-seed seed]`` over UDP on loopback, in lock step, for ``seconds`` of the path; with ``load``, in real time
    beside that many busy processes (nice 3), up to three tries for a run that completes.  Returns the bridge's report
    (its cycles, missed deadlines, skipped cycles, faults and how it ended; with ``load``, each try's)."""
    from pusupu_jax.params import ParameterError
    from pusupu_jax.sim_robot.lockstep import bridge_run

    keys = ("cycles", "missed_deadlines", "skipped_cycles", "faults", "ended")
    tries = []
    for _ in range(1 if load is None else 3):
        busy = [
            subprocess.Popen(["nice", "-n", "3", sys.executable, "-c", "while True: pass"]) for _ in range(load or 0)
        ]
        try:
            report = bridge_run(
                gain_path, trajectory, tmp / f"{robot}.yaml", seconds=seconds, fine_steps=fine_steps,
                log=tmp / f"{robot}.mcap", noise_seed=seed, lockstep=load is None,
            )  # fmt: skip
            tries.append({k: report.get(k) for k in keys})
        except ParameterError as e:  # in real time: a run the robot's drives stopped (a stall past their watchdog)
            if load is None:
                raise SystemExit(f"bench_identify: {e}") from None
            tries.append({"ended": "failed", "error": str(e)[-300:]})
        finally:
            for p in busy:
                p.kill()
                p.wait()
        if load is None:
            return tries[-1]
        if tries[-1]["ended"] == "completed":
            return tries[-1] | {"tries": tries}
    raise SystemExit(f"bench_identify: no bridge run completed in real time: {tries}")


def _noisy(log, seed: int, bits: int, current_noise: float):
    """``log`` as sensors would give it: angles on an encoder of ``bits`` a turn, currents with Gaussian noise of
    ``current_noise`` of each axis's RMS.  Where an encoder's counts fall against the motor's angle depends on how it
    was mounted: each seed draws that phase, per axis, uniformly within one count (with one phase for every seed,
    the rounding would be the same error in every copy of the log)."""
    rng = np.random.default_rng(seed)
    count = 2 * np.pi / 2**bits
    current = log.current + current_noise * np.sqrt(np.mean(log.current**2, axis=0)) * rng.normal(
        size=log.current.shape
    )
    phase = rng.uniform(size=log.position.shape[1])
    return dataclasses.replace(log, position=(np.round(log.position / count + phase) - phase) * count, current=current)


def _entries(report, truth) -> list[dict]:
    """Per fitted value: truth, fit, standard error, relative error, and whether 1.96 standard errors cover it
    (:meth:`pusupu_jax.machine_fit.FittedValue.against`)."""
    keys = ("name", "true", "start", "std_error", "relative_error", "covered_95", "excited", "step_correction")
    return [
        {k: e[k] for k in keys} | {"fitted": e["value"], "abs_error": abs(e["error"])}
        for e in (v.against(truth) for v in report.values)
    ]


def main() -> None:
    from pusupu_jax import machine_fit

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--source",
        choices=("sim", "bridge"),
        default="sim",
        help="the log: pusupu sim's (the fitting model) or pusupu bridge's against pusupu sim-robot (C MuJoCo)",
    )
    ap.add_argument("--trajectory", default="p2p")
    ap.add_argument(
        "--fine-steps",
        type=int,
        help="with --source bridge: the simulated robot steps its machine this many times per current-loop tick, a "
        "truth finer than the fitting model (default: the model's stepping)",
    )
    ap.add_argument(
        "--window", type=float, default=machine_fit.WINDOW_S, help="seconds of the log fitted (default: identify's)"
    )
    ap.add_argument("--mech-step", type=float, help="the replay's mechanical step [s] (default the model's)")
    ap.add_argument("--fit", default="friction,motor,payload")
    ap.add_argument(
        "--step-check",
        type=float,
        metavar="S",
        help="identify's step check: the fitted values replayed at this finer step and moved by one Gauss-Newton step "
        "(default none: the benchmark names it, where pusupu identify takes 0.00005 for a robot's logs)",
    )
    ap.add_argument("--noise-seeds", type=int, default=0, help="noisy copies of the log fitted after it")
    ap.add_argument("--first-seed", type=int, default=0, help="the first noisy copy's seed (default 0)")
    ap.add_argument("--noisy-only", action="store_true", help="fit the noisy copies only, not the noise-free log")
    ap.add_argument(
        "--merge",
        nargs="+",
        metavar="JSON",
        help="no fit: one result from these results of the same settings (say, seeds fitted in several processes)",
    )
    ap.add_argument("--encoder-bits", type=int, default=17)
    ap.add_argument("--current-noise", type=float, default=0.01, help="of each axis's RMS current (default 0.01)")
    ap.add_argument(
        "--true-com",
        default="0.03,-0.02,0.05",
        help="the true payload's centre of mass x,y,z [m] in the platform frame (default 0.03,-0.02,0.05)",
    )
    ap.add_argument(
        "--derivatives",
        default="exact",
        help="the solvers and Jacobians to fit each log with, in order: exact, finite-differences, mujoco-minimize "
        "(default exact)",
    )
    ap.add_argument(
        "--robot-sensors",
        metavar="BITS,AMPS",
        help="with --source bridge: the simulated robot's own sensors, encoders of BITS a turn and current noise of "
        "AMPS (standard deviation), on every axis (the drives' loops close on what they read; default ideal)",
    )
    ap.add_argument(
        "--seeds-in-loop",
        action="store_true",
        help="with --source bridge: each noise seed a bridge run of its own, the simulated robot's sensors drawn from "
        "it inside the loop (pusupu sim-robot --noise-seed), not noise added to one log",
    )
    ap.add_argument(
        "--known-encoders",
        action="store_true",
        help="with the robot's sensors (--robot-sensors or --seeds-in-loop): the start machine file gives its "
        "encoders, so that identify's replay takes the drives' speed from their counts (default: none given)",
    )
    ap.add_argument(
        "--realtime",
        type=int,
        metavar="LOAD",
        help="with --source bridge: the bridge in real time, not lock step, beside LOAD busy processes (nice 3), so "
        "that its cycles go late and are skipped as on a loaded host (default: lock step)",
    )
    ap.add_argument(
        "--timing",
        default="with",
        help="with --source bridge: fit each log with its run's timing (with: identify's replay of the bridge's "
        "commands as the robot ran them), without it (without: every row in turn, one command a period), or both "
        "(with,without; default with)",
    )
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    if args.merge:
        emit(merge([json.loads(Path(f).read_text()) for f in args.merge]), args.out)
        return
    timings = args.timing.split(",")
    if not timings or set(timings) - {"with", "without"}:
        ap.error(f"--timing: expected with, without or both, got {args.timing!r}")
    if args.realtime is not None and (args.source != "bridge" or args.realtime < 0 or args.seeds_in_loop):
        ap.error(
            f"--realtime: expected --source bridge without --seeds-in-loop and a load of 0 or more, got --source "
            f"{args.source} and {args.realtime}"
        )
    if args.noisy_only and args.noise_seeds < 1:
        ap.error(f"--noisy-only: expected --noise-seeds of at least 1, got {args.noise_seeds}")
    if args.known_encoders and not (args.robot_sensors or args.seeds_in_loop):
        ap.error("--known-encoders: expected the robot's sensors (--robot-sensors or --seeds-in-loop), got neither")
    if args.seeds_in_loop and (args.source != "bridge" or args.robot_sensors):
        ap.error(
            "--seeds-in-loop: expected --source bridge without --robot-sensors (the seeds' sensors are given by "
            f"--encoder-bits and --current-noise), got --source {args.source} --robot-sensors {args.robot_sensors}"
        )

    from pusupu_jax import gains as gain_files
    from pusupu_jax import machine_file, machine_fit, run_log
    from pusupu_jax.experiments import real2sim
    from pusupu_jax.files import write_atomic
    from pusupu_jax.runtime import setup_jax

    try:
        methods = [machine_fit.Derivatives(m) for m in args.derivatives.split(",")]
    except ValueError:
        known = ", ".join(map(str, machine_fit.Derivatives))
        ap.error(f"--derivatives: expected names among {known}, got {args.derivatives!r}")
    setup_jax()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        sensors = None
        if args.robot_sensors:
            bits, amps = args.robot_sensors.split(",")
            sensors = (int(bits), float(amps))
        truth = _machines(tmp, tuple(float(c) for c in args.true_com.split(",")), sensors)
        if args.known_encoders:
            counts = np.full(6, 2 ** (sensors[0] if sensors else args.encoder_bits))
            start = dataclasses.replace(machine_file.load(tmp / "start.yaml"), encoder_counts=counts)
            write_atomic(tmp / "start.yaml", machine_file.template(start))
        gain_path = real2sim.table1_gain_file(tmp)
        t0 = time.perf_counter()
        seconds = args.window + 0.5
        if args.source == "bridge":
            run = _bridge_log(tmp, gain_path, args.trajectory, seconds, args.fine_steps, load=args.realtime)
        else:
            _sim_log(tmp, gain_path, args.trajectory)
            run = None
        sim_s = time.perf_counter() - t0
        log = run_log.drive_log(tmp / "true.mcap")
        current_rms = None if log.current is None else np.sqrt(np.mean(log.current**2, axis=0)).tolist()
        start = machine_file.load(tmp / "start.yaml")
        g = gain_files.load(gain_path)
        fields = machine_fit.fit_fields(args.fit)
        seeds = range(args.first_seed, args.first_seed + args.noise_seeds)
        if args.seeds_in_loop:  # the robot's own sensors: the current noise a fraction of each axis's RMS above
            sensed = _sensed(truth, args.encoder_bits, args.current_noise * np.asarray(current_rms))
            write_atomic(tmp / "sensed.yaml", machine_file.template(sensed))

        def in_loop(seed: int):
            """The log of a bridge run against the robot with sensors, their noise drawn from ``seed``."""
            t0 = time.perf_counter()
            robot = _bridge_log(tmp, gain_path, args.trajectory, seconds, args.fine_steps, "sensed", seed)
            print(f"bench_identify: bridge run of seed {seed}: {robot}", file=sys.stderr, flush=True)
            return run_log.drive_log(tmp / "sensed.mcap"), robot | {"wall_s": time.perf_counter() - t0}

        def on_the_log(seed: int):
            """The log with the sensors' noise of ``seed`` added."""
            return _noisy(log, seed, args.encoder_bits, args.current_noise), run

        cases = [] if args.noisy_only else [("noise-free", lambda: (log, run))]
        cases += [
            (f"noise seed {k}", functools.partial(in_loop if args.seeds_in_loop else on_the_log, k)) for k in seeds
        ]
        fits = []
        for (name, make), derivatives, timing in ((c, m, t) for c in cases for m in methods for t in timings):
            if derivatives == methods[0] and timing == timings[0]:
                case, case_run = make()
            print(f"bench_identify: fitting {name} ({derivatives} Jacobian, {timing} timing)", file=sys.stderr)
            report, _, _ = machine_fit.fit(
                [case if timing == "with" else dataclasses.replace(case, timing=None)],
                start, g.servo, g.hybrid, g.rates, fields, args.window,
                progress=lambda line: print(line, file=sys.stderr, flush=True), derivatives=derivatives,
                mech_step=args.mech_step, step_check=args.step_check,
            )  # fmt: skip
            entries = _entries(report, truth)
            per_call = report.residual_s / max(report.residual_calls, 1)
            fits.append(
                {
                    "case": name,
                    "derivatives": str(derivatives),
                    # the replay: of the bridge's commands as the run's timing says the robot ran them, or of every
                    # row in turn (a log without timing: pusupu sim's, or without --timing's with)
                    "timing": timing if case.timing is not None else "none in the log",
                    "timing_counts": report.logs[0]["timing"],  # what the timing changed in the replay (with it)
                    "bridge_run": case_run,  # the run whose log this is (with --seeds-in-loop, the seed's own)
                    "wall_s": report.wall_s,
                    "solve_s": report.residual_s + report.jacobian_s,
                    "residual_calls": report.residual_calls,
                    "residual_s": report.residual_s,
                    "jacobian_s": report.jacobian_s,
                    "replays": report.residual_calls + report.jacobian_s / per_call,
                    "mech_step_s": report.mech_step_s,
                    "evaluations": report.evaluations,
                    "jacobians": report.jacobians,
                    "converged": report.converged,
                    "message": report.solver_message,  # the solver's reason to stop
                    "residual_rms_before": report.residual_rms_before,
                    "residual_rms_after": report.residual_rms_after,
                    # with --step-check: that replay's residual RMS at the values fitted and at the values moved
                    "step_check_rms": report.step_check_rms,
                    "step_check_wall_s": report.step_check_wall_s,
                    "worst_relative_error": max(e["relative_error"] for e in entries),
                    # after each residual call: seconds of calls so far, the least residual RMS met so far
                    "trace": [[round(t, 4), rms] for t, rms in report.trace],
                    "covered_95": sum(e["covered_95"] for e in entries),
                    "values": entries,
                    # the pairs of values the log tells apart only in combination (|correlation| >= 0.5)
                    "strongest_correlations": machine_fit.strongest_correlations(
                        report.values, report.correlation, most=10
                    ),
                }
            )
            summary = _summary(args, fields, report.samples, sim_s, fits, current_rms) | {"bridge_run": run}
            print(
                f"bench_identify: {name}: worst relative error {fits[-1]['worst_relative_error']:.3g}, "
                f"{fits[-1]['covered_95']} of {len(entries)} inside their 95 % intervals, {report.wall_s:.0f} s",
                file=sys.stderr,
                flush=True,
            )
            if args.out:  # each fit as it ends: a long run stopped early keeps what it found
                write_atomic(args.out, json.dumps(summary, indent=1) + "\n")
    emit(summary, args.out)


SAME_RESIDUAL = 1e-6  # two residual RMS are the same to this fraction: a floor's last digits are no progress


def anchors(fits: list[dict]) -> list[dict]:
    """Each fit of another solver against the exact fit of the same log: the ratios of their solve and wall times
    and replays, and the seconds each took to the same residual (the higher of the two fits' least, to
    :data:`SAME_RESIDUAL`): on a log the model cannot match, a solver may spend long on the floor's last digits."""
    exact = {(f["case"], f.get("timing")): f for f in fits if f["derivatives"] == "exact"}
    out = []
    for f in fits:
        other = exact.get((f["case"], f.get("timing")))
        if f["derivatives"] == "exact" or other is None:
            continue
        level = max(other["trace"][-1][1], f["trace"][-1][1])
        reached = [next(t for t, rms in g["trace"] if rms <= level * (1 + SAME_RESIDUAL)) for g in (other, f)]
        out.append(
            {
                "case": f["case"],
                "derivatives": f["derivatives"],
                "solve_s_ratio": f["solve_s"] / other["solve_s"],
                "wall_s_ratio": f["wall_s"] / other["wall_s"],
                "replays_ratio": f["replays"] / other["replays"],
                "residual_rms_after": [other["residual_rms_after"], f["residual_rms_after"]],
                "same_residual_rms": level,
                "seconds_to_same_residual": reached,
                "same_residual_ratio": reached[1] / reached[0],
            }
        )
    return out


def _summary(args, fields, samples: int, sim_s: float, fits: list[dict], current_rms: list[float] | None) -> dict:
    """The benchmark's JSON over the fits done so far."""
    import jax

    anchor = anchors(fits)
    return {
        "benchmark": "identify",
        "command": "python benchmarks/bench_identify.py " + " ".join(sys.argv[1:]),
        "source": args.source,
        "trajectory": args.trajectory,
        "robot_fine_steps": args.fine_steps if args.source == "bridge" else None,
        "realtime_load": args.realtime,  # the bridge in real time beside this many busy processes (None: lock step)
        "window_s": args.window,
        "mech_step_s": fits[0]["mech_step_s"],
        "step_check_s": args.step_check,
        "fit": [str(f) for f in fields],
        "values_fitted": len(fits[0]["values"]),
        "derivatives": args.derivatives.split(","),
        "samples": samples,
        # in_loop: each seed the robot's own sensors in a bridge run of its own (--seeds-in-loop), else noise on one log
        "noise": {
            "encoder_bits": args.encoder_bits,
            "current_rms_fraction": args.current_noise,
            "in_loop": args.seeds_in_loop,
        },
        "known_encoders": args.known_encoders,  # the start machine gives the robot's encoders
        "true_payload_com_m": [float(c) for c in args.true_com.split(",")],
        "robot_sensors": args.robot_sensors,
        "log_current_rms_a": current_rms,
        "sim_log_s": sim_s,
        "fits": fits,
        "anchor": anchor,  # the other Jacobians against the exact one, per log (a ratio above 1: exact is faster)
        "machine": {"processor": processor(), "cores": os.cpu_count(), "jax": jax.__version__},
    } | coverage(fits)


def _solver(fit: dict) -> str:
    """A fit's solver, and ", without timing" where its replay left the bridge log's timing out (``--timing``)."""
    return fit["derivatives"] + (", without timing" if fit.get("timing") == "without" else "")


def coverage(fits: list[dict]) -> dict:
    """Per solver (``coverage``, keyed by its name), over its fits of noisy logs: how many (``noisy_fits``), the share
    of all 95 % intervals that cover the truth (``coverage_95``), and per value (``per_value``) the share of seeds whose
    interval covers it and the worst relative error, with the least share and the worst error over the values; and
    ``error_in_std_errors``, the median and the largest of each excited value's error in its standard errors (intervals
    of the right width give a median near 0.67, the normal distribution's)."""
    out = {}
    for solver in dict.fromkeys(map(_solver, fits)):
        noisy = [f for f in fits if _solver(f) == solver and f["case"] != "noise-free"]
        if not noisy:
            continue
        per_value = {
            e["name"]: {
                "covered_95": float(np.mean([f["values"][i]["covered_95"] for f in noisy])),
                "worst_relative_error": max(f["values"][i]["relative_error"] for f in noisy),
                "excited": sum(f["values"][i]["excited"] for f in noisy),
            }
            for i, e in enumerate(noisy[0]["values"])
        }
        ratios = [
            v["abs_error"] / v["std_error"] for f in noisy for v in f["values"] if v["excited"] and v["std_error"]
        ]
        out[solver] = {
            "noisy_fits": len(noisy),
            "coverage_95": sum(f["covered_95"] for f in noisy) / sum(len(f["values"]) for f in noisy),
            "least_coverage_95": min(v["covered_95"] for v in per_value.values()),
            "worst_relative_error_noisy": max(v["worst_relative_error"] for v in per_value.values()),
            "per_value": per_value,
            "error_in_std_errors": {"median": float(np.median(ratios)), "max": float(np.max(ratios))},
        }
    return {"coverage": out}


SETTINGS = (
    *("source", "trajectory", "robot_fine_steps", "robot_sensors", "window_s", "mech_step_s", "fit", "noise"),
    *("true_payload_com_m", "step_check_s", "known_encoders", "realtime_load"),
)


def merge(results: list[dict]) -> dict:
    """One result from ``results`` of the same settings (:data:`SETTINGS`): their fits, each case once, and the
    coverage over all of them; ``commands`` and ``machines`` list each part's (a merged part's own lists)."""
    # the coverage is computed afresh below (a part's own, or one of an older layout, left out)
    stale = ("coverage", "noisy_fits", "coverage_95", "least_coverage_95", "worst_relative_error_noisy", "per_value")
    first = {k: v for k, v in results[0].items() if k not in stale}
    for r in results[1:]:
        differ = [k for k in SETTINGS if r.get(k) != first.get(k)]
        if differ:
            raise SystemExit(f"bench_identify: --merge: expected results of the same settings, found {differ} differ")
    fits = {(f["case"], f["derivatives"]): f for r in results for f in r["fits"]}
    ordered = sorted(
        fits.values(),
        key=lambda f: (f["derivatives"], -1 if f["case"] == "noise-free" else int(f["case"].split()[-1])),
    )
    solvers = list(dict.fromkeys(f["derivatives"] for f in ordered))
    commands = [c for r in results for c in r.get("commands", [r["command"]])]
    machines = [m for r in results for m in r.get("machines", [r["machine"]])]
    return (
        first
        | {"command": None, "commands": commands, "machines": machines, "machine": None, "derivatives": solvers}
        | coverage(ordered)
        | {
            "fits": ordered,
            "anchor": anchors(ordered),
        }
    )


if __name__ == "__main__":
    main()
