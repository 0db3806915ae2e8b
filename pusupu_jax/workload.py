"""Bounds on the work one command may be asked for (host-side): every duration, rate, horizon and count given on the
command line or in a file is checked against the work it implies, before anything is built or compiled, with one line
that gives the limit.

A run's cost is its steps times the state each step advances, counted where it is spent:

* *current-loop ticks*: every plant runs the six drives' current loops, filters and motor electrics at
  ``rates.f_current``, a tick each (a few dozen numbers of state); a 100 kHz current loop, the fastest a file may
  hold (:func:`pusupu_jax.stability.check_rates`), costs 5 times the default 20 kHz per simulated second;
* *mechanical steps* of the MJX machine, one every ``ModelOptions.timestep`` (0.25 ms): the whole mechanism's
  state, its kinematics and its constraint forces, far dearer than a tick;
* *trace entries*: a run keeps one per position period (about 1 kB each), so that a short position period fills
  memory where ticks alone would not.

A tuning run costs its gradients (their steps are also what reverse mode keeps in memory) and its forward passes
over the whole paths (:func:`pusupu_jax.tune.run.check_work` counts them).  The limits are far above every default and
documented run, and below what ends in an exhausted memory or a run of days.
"""

from __future__ import annotations

from .params import LoopRates, ParameterError

MAX_TICKS = 40_000_000  # current-loop ticks of one command: 2000 s at the default 20 kHz (under a minute here)
MAX_PERIODS = 2_000_000  # position periods kept in the traces of one command (about 2 GB)
MAX_MACHINE_STEPS = 4_000_000  # mechanical steps of the MJX machine in one command: 1000 s, 23 arcs of the paper
MAX_GRADIENT_STEPS = 1_000_000  # mechanical steps in one tuning gradient: 40 times the default tune's 24 000
MAX_TUNE_STEPS = 500_000_000  # mechanical steps of one tuning problem: about 100 times the default tune's 4.6 million


def check_run(
    where: str, seconds: float, rates: LoopRates, *, machine: bool = False, error: type[Exception] = ParameterError
) -> None:
    """``seconds`` [s] simulated in all by one command at ``rates`` (``machine``: on the MJX machine, whose mechanism
    steps every ``rates.dt_mech`` s): at most :data:`MAX_TICKS` current-loop ticks, :data:`MAX_PERIODS` position
    periods and (``machine``) :data:`MAX_MACHINE_STEPS` mechanical steps; ``error`` naming ``where`` and the limit in
    seconds at these rates otherwise."""
    limits = [
        (MAX_TICKS, rates.dt_current, f"current-loop ticks of {rates.dt_current * 1e6:.3g} us"),
        (MAX_PERIODS, rates.dt_position, f"position periods of {rates.dt_position * 1e3:.3g} ms kept in the trace"),
    ]
    if machine:
        limits.append((MAX_MACHINE_STEPS, rates.dt_mech, f"mechanical steps of {rates.dt_mech * 1e3:.3g} ms"))
    for most, dt, what in limits:
        if not seconds <= most * dt:
            raise error(
                f"{where}: expected at most {most * dt:g} s at these rates ({most:.3g} {what}), got {seconds:g} s"
            )


def check_tuning(
    where: str, gradient_steps: float, total_steps: float, error: type[Exception] = ParameterError
) -> None:
    """A tuning problem of ``gradient_steps`` mechanical steps in one gradient and ``total_steps`` in all: at most
    :data:`MAX_GRADIENT_STEPS` and :data:`MAX_TUNE_STEPS`; ``error`` naming ``where`` and the limit otherwise."""
    for steps, most, what in (
        (
            gradient_steps,
            MAX_GRADIENT_STEPS,
            "in one gradient (scenarios x windows x window length; reverse mode keeps them in memory)",
        ),
        (
            total_steps,
            MAX_TUNE_STEPS,
            "in all (gradients over the iterations and starts, forward passes over the whole paths)",
        ),
    ):
        if steps > most:
            raise error(f"{where}: expected at most {most:.3g} mechanical steps of the machine {what}, got {steps:.3g}")
