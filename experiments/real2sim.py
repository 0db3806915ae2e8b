"""From the robot's data to new gains, measured: on true machines that differ from the nominal one, the gains tuned
on the machine ``pusupu identify`` found against those tuned on the nominal machine and those tuned on the truth.

Each true machine (:func:`true_machines`) is the built-in one with other drive-train friction (x0.5 to x3), torque
and back-EMF constants (-10 to +10 %), rotor inertias and a payload of 1 to 10 kg off the platform's centre; a fifth
is the third with seeded kinematic errors as well.  It stands in for a robot: ``pusupu sim-robot --machine true.yaml
[--kin-error SEED] --fine-steps``
:data:`FINE_STEPS` (C MuJoCo stepped four times per current-loop tick, finer than the tuner's model), reached by
``pusupu bridge`` over UDP in lock step (:func:`pusupu_jax.sim_robot.lockstep.bridge_run`).  The workflow, as a user
runs it (README, "From your robot's data to new gains"):

1. ``pusupu tune`` on the nominal (built-in) machine from Table 1: the nominal-tuned gains, once; and those gains
   tuned again as long on the nominal machine (the same-budget control, below);
2. per true machine, a logged bridge run on the excitation path (``excite``) with Table 1's gains in IMC
   (:func:`table1_gain_file`), stiffer in the velocity loop than the tuned ones: with the nominal-tuned gains the
   worn machine's axis 5 fell 5.39 mm behind its reference there and the bridge stopped the run (its following-error
   window is 5 mm);
3. ``pusupu identify`` of friction, motor (torque constant, rotor inertia) and payload (mass, centre of mass) from
   that log, starting from the machine as designed (the built-in one with a 3 kg payload guessed at the centre; the
   payload's inertia given as the truth's, as from CAD), with its step check at :data:`STEP_CHECK_S` (the robot is
   finer than the replay);
4. ``pusupu tune`` on the identified machine, and on the true machine itself (its kinematic errors, if any), both
   from the nominal-tuned gains;
5. a bridge run on the task path (:data:`TASK_PATH`) with each gain set against the true machine.

The identified- and truth-tuned gains have had two tunings, the nominal-tuned ones one.  So that the payoff
measures the machine and not the extra iterations, the nominal-tuned gains tuned again on the nominal machine with
the same configuration (:attr:`TunedOn.NOMINAL_AGAIN`) run as well, and the gap is taken against them too.

The tunings are IMC (``lambda1, lambda2, T0, Kv, Tv``) on the task path with the default windows and iterations, so
that the bridge runs every drive in cyclic synchronous velocity at 1 kHz.  Reported per true machine: the identified
values against the truth, the platform's RMS and max error of each gain set on the bridge, and the share of the gap
between the nominal-tuned and the truth-tuned gains' RMS error that the identified-tuned gains close
(:func:`gap_closed`), from the nominal-tuned gains and from the same budget's; the same for the sliders' RMS error from
their references (``slider_rms_error_mm``, the RMS over the six branches), which the gains act on.  The summary's count
against :data:`TARGET` takes the machines without kinematic errors: where the robot has them, the platform's error
holds their share as well, which no gains remove, so that machine is reported apart (``docs/identify.md`` has the
figures).  A bridge run that ends in a safe stop is reported with its faults, its errors over the cycles before
it.  ``quick`` runs one true machine on the task path's first :data:`QUICK_S` seconds with a few iterations: a check of
the workflow, not a measurement.  The full run takes about 25 min a machine on a 2-core CPU, and 20 min for the two
tunings on the nominal machine.
"""

from __future__ import annotations

import dataclasses
import enum
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from pusupu_jax import gains as gain_files
from pusupu_jax import machine_file, machine_fit, run_log
from pusupu_jax.files import write_atomic
from pusupu_jax.machine_file import Machine, Payload
from pusupu_jax.params import LoopRates, ParameterError
from pusupu_jax.plots import save_atomic
from pusupu_jax.sim_robot.lockstep import bridge_run

from . import Result

TASK_PATH = "arc"
EXCITATION_PATH = "excite"
FINE_STEPS = 4  # the simulated robot's mechanical steps per current-loop tick
FIT = "friction,motor,payload"
DESIGNED_PAYLOAD_KG = 3.0  # the machine as designed: a payload guessed at the platform's centre
QUICK_S = 2.0  # s of the task path in the quick run
TARGET = 0.7  # the share of the gap the identified-tuned gains should close
MIN_GAP = 0.01  # a gap below this share of the truth-tuned gains' error is no gap (gap_closed)
# identify's step check [s] (pusupu identify --step-check): one step a current-loop tick, identify's own default for a
# robot's logs (machine_fit.default_step_check).  The robot steps its machine finer than the replay, and without the
# check the values on the loaded machine came up to 3.6 % off, and the gains tuned on them closed 23 % of the gap;
# with it, 0.5 % and 102 % (docs/identify.md)
STEP_CHECK_S = LoopRates().dt_current


class TunedOn(enum.StrEnum):
    """Whose machine a gain set was tuned on; ``NOMINAL_AGAIN``: the nominal-tuned gains tuned again on the nominal
    machine, the budget of the identified- and truth-tuned sets (each tuned from the nominal-tuned gains)."""

    NOMINAL = "nominal"
    NOMINAL_AGAIN = "nominal again"
    IDENTIFIED = "identified"
    TRUTH = "truth"

    @property
    def words(self) -> str:
        """The gain set in words: "tuned on the ... machine"."""
        return {
            TunedOn.NOMINAL: "tuned on the nominal machine",
            TunedOn.NOMINAL_AGAIN: "tuned twice on the nominal machine",
            TunedOn.IDENTIFIED: "tuned on the identified machine",
            TunedOn.TRUTH: "tuned on the true machine",
        }[self]

    @property
    def folder(self) -> str:
        """The tune's output folder's name."""
        return f"tuned_{self.name.lower()}"


@dataclasses.dataclass(frozen=True)
class TrueMachine:
    """A hidden true machine: ``machine`` (its file), ``kin_error_seed`` (the robot's seeded kinematic errors; None:
    none) and ``differs`` (how it differs from the nominal machine, in words)."""

    machine: Machine
    kin_error_seed: int | None
    differs: str


def true_machines() -> list[TrueMachine]:
    """Four machines that differ from the built-in one in every value ``identify`` fits, within the ranges a shop
    sees: friction x0.5 to x3, torque constants -10 to +10 % (the back-EMF constants with them, in SI units equal),
    rotor inertias -15 to +30 %, payloads of 1 to 10 kg, each off the platform's centre; and the third again with
    seeded kinematic errors (seed 3: the rail points, platform joints and rod lengths off by 0.5 mm standard
    deviation)."""
    base = Machine.default()
    d = base.drives

    def unseeded(name, coulomb, viscous, kt, rotor, payload, differs) -> TrueMachine:
        """The built-in machine with its drives' values scaled per axis, and ``payload``; no kinematic errors."""
        drives = d | {
            "coulomb": d["coulomb"] * np.asarray(coulomb, float),
            "viscous": d["viscous"] * np.asarray(viscous, float),
            "Kt": d["Kt"] * np.asarray(kt, float),
            "Ke": d["Ke"] * np.asarray(kt, float),
            "J": d["J"] * np.asarray(rotor, float),
        }
        return TrueMachine(dataclasses.replace(base, name=name, drives=drives, payload=payload), None, differs)

    cases = [
        unseeded(
            "worn",
            [3.0, 2.5, 2.8, 3.0, 2.2, 2.6],
            [2.0, 3.0, 2.4, 2.8, 2.0, 2.6],
            [0.90, 0.92, 0.95, 0.90, 0.93, 0.91],
            [1.1, 1.3, 1.2, 1.25, 1.15, 1.3],
            Payload(10.0, (0.05, 0.03, 0.08), (0.06, 0.05, 0.09)),
            "friction x2.2-3, Kt -5 to -10 %, rotors +10-30 %, 10 kg payload off centre",
        ),
        unseeded(
            "run-in",
            [0.5, 0.6, 0.55, 0.5, 0.65, 0.6],
            [0.5, 0.6, 0.7, 0.5, 0.55, 0.65],
            [1.10, 1.08, 1.05, 1.10, 1.07, 1.09],
            [0.85, 0.9, 0.95, 0.85, 0.9, 0.95],
            Payload(1.0, (-0.04, 0.02, 0.03), (0.004, 0.004, 0.006)),
            "friction x0.5-0.7, Kt +5 to +10 %, rotors -5 to -15 %, 1 kg payload off centre",
        ),
        unseeded(
            "mixed",
            [1.4, 0.8, 2.0, 1.2, 0.7, 1.6],
            [0.7, 1.5, 1.2, 2.0, 0.8, 1.1],
            [1.05, 0.93, 1.0, 0.96, 1.06, 0.92],
            [1.2, 0.9, 1.1, 1.0, 1.3, 0.85],
            Payload(5.0, (0.03, -0.02, 0.05), (0.02, 0.02, 0.03)),
            "friction x0.7-2, Kt -8 to +6 %, rotors -15 to +30 %, 5 kg payload off centre",
        ),
        unseeded(
            "loaded",
            [1.2, 1.5, 1.0, 1.3, 1.1, 1.4],
            [1.5, 1.2, 1.8, 1.0, 1.4, 1.6],
            [0.94, 0.97, 0.92, 0.95, 0.98, 0.93],
            [1.2, 1.1, 1.25, 1.15, 1.3, 1.05],
            Payload(8.0, (-0.04, 0.04, 0.06), (0.045, 0.04, 0.07)),
            "friction x1-1.8, Kt -2 to -8 %, rotors +5-30 %, 8 kg payload off centre",
        ),
    ]
    mixed = cases[2]
    seeded = dataclasses.replace(mixed.machine, name="mixed, with kinematic errors")
    return cases + [TrueMachine(seeded, 3, mixed.differs + ", seeded kinematic errors")]


def as_designed(truth: Machine) -> Machine:
    """Where identification starts: the built-in machine with a :data:`DESIGNED_PAYLOAD_KG` payload at the platform's
    centre, its inertia the truth's (as from CAD: the fit leaves it alone)."""
    return dataclasses.replace(
        Machine.default(),
        name="as designed",
        payload=Payload(DESIGNED_PAYLOAD_KG, (0.0, 0.0, 0.0), truth.payload.inertia),
    )


def table1_gain_file(folder: Path) -> Path:
    """Table 1's gains in IMC, written as the built-in machine's gain file ``folder/gains.yaml``."""
    from pusupu_jax import LoopRates, ServoParams
    from pusupu_jax.hybrid import HybridGains

    return gain_files.write(folder / "gains.yaml", ServoParams.table1(), HybridGains(), LoopRates(), mode="imc")


def gap_closed(nominal: float, identified: float, truth: float) -> float:
    """The share of the RMS-error gap between the nominal-tuned and the truth-tuned gains that the identified-tuned
    gains close: 1 where they track as the truth-tuned ones, 0 as the nominal-tuned ones, below 0 where worse; NaN
    where there is no gap to close: the truth-tuned gains better by less than :data:`MIN_GAP` of their own error (a
    share of a smaller gap says nothing of the identification: a gap of 0.2 % once gave -130 %)."""
    gap = nominal - truth
    return float((nominal - identified) / gap) if gap > MIN_GAP * truth else float("nan")


GAP_KEYS = ("gap_closed", "slider_gap_closed", "gap_closed_same_budget", "slider_gap_closed_same_budget")


def gaps(runs: dict[TunedOn, dict]) -> dict[str, float]:
    """The shares of the gap the identified-tuned gains close (:func:`gap_closed`), keyed as :data:`GAP_KEYS`: of the
    platform's RMS error and the sliders' (``slider_``), from the nominal-tuned gains and from those tuned twice on
    the nominal machine (``_same_budget``).  ``runs``: per gain set, its bridge run's ``rms_tracking_error_mm`` and
    ``slider_rms_error_mm``."""
    return {
        f"{prefix}gap_closed{suffix}": gap_closed(
            *(runs[s][error] for s in (control, TunedOn.IDENTIFIED, TunedOn.TRUTH))
        )
        for prefix, error in (("", "rms_tracking_error_mm"), ("slider_", "slider_rms_error_mm"))
        for suffix, control in (("", TunedOn.NOMINAL), ("_same_budget", TunedOn.NOMINAL_AGAIN))
    }


def _config(quick: bool):
    from pusupu_jax.tune.config import TuneConfig

    cfg = TuneConfig(mode="imc", groups=("imc", "velocity"), trajectories=(TASK_PATH,), baselines=())
    if quick:
        cfg = cfg.replace(path_s=QUICK_S, windows=2, window_s=0.3, refresh_every=1, iterations=3)
    return cfg


def _say(line: str) -> None:
    print(f"real2sim: {line}", file=sys.stderr, flush=True)


def _tune(cfg, out: Path, machine: Machine, start) -> dict:
    """``pusupu tune`` of ``machine`` from ``start`` into ``out``; the objective before and after, and the wall time."""
    from pusupu_jax.tune.job import run_job

    report, status = run_job(cfg, out, machine=machine, start=start)
    if status:
        raise ParameterError(f"tune on {machine.name!r}: no gains exported: {report.export.error}")
    return {
        "objective_before": report.objective_before,
        "objective_after": report.objective_after,
        "wall_s": report.wall_s,
    }


def _case(
    t: TrueMachine,
    folder: Path,
    nominal: dict[TunedOn, Path],
    excitation: Path,
    cfg,
    quick: bool,
    step_check: float | None,
) -> dict:
    """One true machine through the workflow (module docstring, steps 2 to 5); ``nominal``: the gain files tuned on
    the nominal machine (:attr:`TunedOn.NOMINAL`, :attr:`TunedOn.NOMINAL_AGAIN`), ``excitation``: the gain file of the
    excitation run; ``step_check``: identify's (:func:`pusupu_jax.machine_fit.fit`), or None."""
    name = t.machine.name
    true_file = folder / "true.yaml"
    write_atomic(true_file, machine_file.template(t.machine))
    _say(f"{name}: a logged bridge run on {EXCITATION_PATH!r} with Table 1's gains")
    log_file = folder / "excite.mcap"
    excite = bridge_run(
        excitation, EXCITATION_PATH, true_file, seconds=machine_fit.WINDOW_S + 0.5, fine_steps=FINE_STEPS,
        kin_error=t.kin_error_seed, log=log_file,
    )  # fmt: skip
    start = as_designed(t.machine)
    g = gain_files.load(excitation)
    _say(f"{name}: identify {FIT} from the machine as designed (a few minutes)")
    report, identified, _ = machine_fit.fit(
        [run_log.drive_log(log_file)], start, g.servo, g.hybrid, g.rates, machine_fit.fit_fields(FIT),
        progress=lambda line: _say(f"{name}: {line}"), step_check=step_check,
    )  # fmt: skip
    identified = dataclasses.replace(identified, name=f"{name}, identified")
    identified_file = folder / "identified.yaml"
    write_atomic(identified_file, machine_file.template(identified))
    tunes, gain_paths = {}, dict(nominal)
    for label, machine, config in (
        (TunedOn.IDENTIFIED, identified, cfg),
        (
            TunedOn.TRUTH,
            t.machine,
            cfg if t.kin_error_seed is None else cfg.replace(kin_error_seeds=(t.kin_error_seed,)),
        ),
    ):
        _say(f"{name}: {label.words.replace('tuned', 'tune', 1)}")
        out = folder / label.folder
        tunes[label] = _tune(config, out, machine, gain_files.load(nominal[TunedOn.NOMINAL], machine=machine))
        gain_paths[label] = out / "gains.yaml"
    runs = {}
    for label in TunedOn:
        bridge_machine = {TunedOn.IDENTIFIED: identified_file, TunedOn.TRUTH: true_file}.get(label)
        _say(f"{name}: the gains {label.words} on {TASK_PATH!r} through the bridge")
        r = bridge_run(
            gain_paths[label], TASK_PATH, true_file, bridge_machine, seconds=QUICK_S if quick else None,
            fine_steps=FINE_STEPS, kin_error=t.kin_error_seed,
        )  # fmt: skip
        runs[label] = {k: r.get(k) for k in ("rms_tracking_error_mm", "max_tracking_error_mm", "cycles", "faults")}
        runs[label]["slider_rms_error_mm"] = float(np.sqrt(np.mean(np.square(r["branch_rms_error_mm"]))))
    return {
        "machine": name,
        "differs": t.differs,
        "kin_error_seed": t.kin_error_seed,
        "excitation_run": {
            k: excite.get(k) for k in ("cycles", "faults", "rms_tracking_error_mm", "max_tracking_error_mm")
        },
        "identify": {
            "residual_rms_before": report.residual_rms_before,
            "residual_rms_after": report.residual_rms_after,
            "step_check_rms": report.step_check_rms,
            "evaluations": report.evaluations,
            "converged": report.converged,
            "wall_s": report.wall_s,
            "values": [v.against(t.machine) for v in report.values],
        },
        "tunes": tunes,
        "runs": runs,
        **gaps(runs),
    }


def run(
    quick: bool = False, cases: Sequence[TrueMachine] | None = None, step_check: float | None = STEP_CHECK_S
) -> Result:
    """The workflow on ``cases`` (default :func:`true_machines`; ``quick``: their first), after the two tunes on the
    nominal machine.  ``step_check`` [s]: identify's step check at that step (``pusupu identify --step-check``;
    default :data:`STEP_CHECK_S`; None: none)."""
    cfg = _config(quick)
    cases = list(true_machines() if cases is None else cases)[: 1 if quick else None]
    with tempfile.TemporaryDirectory(prefix="pusupu-real2sim-") as d:
        folder = Path(d)
        _say("tune on the nominal machine from Table 1")
        nominal = {label: folder / label.folder / "gains.yaml" for label in (TunedOn.NOMINAL, TunedOn.NOMINAL_AGAIN)}
        nominal_tune = _tune(cfg, nominal[TunedOn.NOMINAL].parent, Machine.default(), "table1")
        _say("tune the nominal-tuned gains again on the nominal machine (the same budget as the other sets)")
        again = gain_files.load(nominal[TunedOn.NOMINAL], machine=Machine.default())
        nominal_again_tune = _tune(cfg, nominal[TunedOn.NOMINAL_AGAIN].parent, Machine.default(), again)
        (folder / "table1").mkdir()
        excitation = table1_gain_file(folder / "table1")
        results = []
        for k, t in enumerate(cases):
            (folder / f"machine{k}").mkdir()
            results.append(_case(t, folder / f"machine{k}", nominal, excitation, cfg, quick, step_check))
    return Result(
        "real2sim",
        {
            "task_path": TASK_PATH,
            "duration_s": QUICK_S if quick else None,
            "fine_steps": FINE_STEPS,
            "fit": FIT,
            "step_check_s": step_check,
            "tune": {
                "mode": cfg.mode,
                "groups": list(cfg.groups),
                "windows": cfg.windows,
                "iterations": cfg.iterations,
            },
            "nominal_tune": nominal_tune,
            "nominal_again_tune": nominal_again_tune,
            "machines": results,
            "summary": summary(results),
        },
    )


def summary(cases: list[dict]) -> dict:
    """Over the ``cases`` without kinematic errors (each with its :func:`gaps`): each share per machine, and how many
    reach :data:`TARGET` (a NaN, no gap, reaches nothing)."""
    payoff = [c for c in cases if c["kin_error_seed"] is None]
    closed = {key: [c[key] for c in payoff] for key in GAP_KEYS}
    return {
        "target": TARGET,
        "machines": len(payoff),
        **{f"{key}_reaching_target": sum(bool(c >= TARGET) for c in closed[key]) for key in GAP_KEYS},
        "min_gap": MIN_GAP,
        **closed,
    }


def _share(closed: float) -> str:
    return "no gap" if np.isnan(closed) else f"{100 * closed:.0f} %"


def plot(result: Result, out) -> list:
    m = result.metrics
    cases = m["machines"]
    fig, ax = plt.subplots(figsize=(3 + 3 * len(cases), 5))
    x = np.arange(len(cases))
    width = 0.8 / len(TunedOn)
    for k, label in enumerate(TunedOn):
        values = [c["runs"][label]["rms_tracking_error_mm"] for c in cases]
        ax.bar(x + (k - (len(TunedOn) - 1) / 2) * width, values, width, label=f"the gains {label.words}")
    for i, c in enumerate(cases):
        note = f"gap closed {_share(c['gap_closed'])},\nwith the same budget {_share(c['gap_closed_same_budget'])}"
        ax.annotate(note, (i, 0), xytext=(0, -34), textcoords="offset points", ha="center", fontsize=8)
    ax.set_xticks(x, [c["machine"] for c in cases])
    ax.set_ylabel(f"platform RMS error on {m['task_path']} through the bridge [mm]")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Gains tuned on the nominal, the identified and the true machine, run on the true machine")
    fig.tight_layout()
    return [save_atomic(fig, out / "real2sim.png")]


def table(result: Result) -> str:
    m = result.metrics
    lines = [
        f"Gains tuned on the nominal (once, and twice: the others' budget), the identified and the true machine, each "
        f"run through the bridge on the true machine (sim-robot, {m['fine_steps']} steps a current tick) along "
        f"{m['task_path']}"
        + (f" (first {m['duration_s']:g} s)" if m["duration_s"] else "")
        + ". RMS / max platform error [mm], and the sliders' RMS error from their references [mm]. Gap closed: the "
        "share of the gap between the nominal-tuned (once; twice) and the truth-tuned gains' RMS errors that the "
        "identified-tuned gains close, of the platform's and the sliders'.",
        "",
        "| true machine | identify: residual, worst value | "
        + " | ".join(label.words for label in TunedOn)
        + " | gap closed: platform, sliders | with the same budget |",
        "|---|---|" + "---|" * len(TunedOn) + "---|---|",
    ]
    for c in m["machines"]:
        i = c["identify"]
        worst = max((v for v in i["values"] if v["relative_error"] is not None), key=lambda v: v["relative_error"])
        cells = [
            f"{c['runs'][s]['rms_tracking_error_mm']:.3f} / {c['runs'][s]['max_tracking_error_mm']:.3f}, "
            f"{c['runs'][s]['slider_rms_error_mm']:.3f}"
            + (f" (faulted: {', '.join(map(str, c['runs'][s]['faults']))})" if c["runs"][s]["faults"] else "")
            for s in TunedOn
        ]
        lines.append(
            f"| {c['machine']} ({c['differs']}"
            + ("" if c["kin_error_seed"] is None else f", seed {c['kin_error_seed']}")
            + ") | "
            f"{i['residual_rms_before']:.3g} -> {i['residual_rms_after']:.3g}; {worst['name']} "
            f"{100 * worst['relative_error']:.1f} % off | "
            + " | ".join(cells)
            + f" | {_share(c['gap_closed'])}, {_share(c['slider_gap_closed'])}"
            f" | {_share(c['gap_closed_same_budget'])}, {_share(c['slider_gap_closed_same_budget'])} |"
        )
    s = m["summary"]
    lines += [
        "",
        f"Of the {s['machines']} machine(s) without kinematic errors, {s['gap_closed_reaching_target']} close at "
        f"least {100 * s['target']:.0f} % of the platform error's gap from the nominal-tuned gains "
        f"({s['slider_gap_closed_reaching_target']} of the sliders'), {s['gap_closed_same_budget_reaching_target']} "
        f"from the gains tuned twice on the nominal machine ({s['slider_gap_closed_same_budget_reaching_target']} of "
        f"the sliders'). A gap under {100 * s['min_gap']:.0f} % of the truth-tuned gains' error is no gap.",
    ]
    return "\n".join(lines)
