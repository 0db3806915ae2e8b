"""Simulating the whole machine: platform paths through inverse kinematics into the cascade and the MJX plant.

Host-side entry point :func:`simulate_machine`: checks the path against the geometry
before anything runs (reachability, stroke, conditioning), turns it into branch
references with the nominal inverse kinematics, runs the jitted co-simulation and
reports the metrics of ``pusupu sim --plant mjx``.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from . import metrics
from .params import LoopRates, ServoParams, validate
from .plant import kinematics
from .plant.axis import screw_ratio
from .plant.geometry import Geometry
from .plant.mjx_plant import MJXPlant
from .plant.model import ModelOptions
from .sim import rollout

MACHINE_MODES = ("imc", "pid")


def machine_rates(options: ModelOptions = ModelOptions(), rates: LoopRates = LoopRates()) -> LoopRates:
    """``rates`` with the mechanical step set to the model's timestep."""
    n_mech = rates.f_current * options.timestep
    if abs(n_mech - round(n_mech)) > 1e-9:
        raise ValueError(f"the model timestep {options.timestep} s is not a whole number of current-loop ticks")
    return dataclasses.replace(rates, n_mech=int(round(n_mech)))


@functools.lru_cache(maxsize=8)
def _plant(options: ModelOptions) -> MJXPlant:
    return MJXPlant.create(Geometry.default(), options)


@functools.lru_cache(maxsize=None)
def _runner(plant, rates, mode):
    return jax.jit(functools.partial(rollout, plant_params=None, plant=plant, rates=rates, outer=mode))


def simulate_machine(servo: ServoParams, path, *, mode: str = "imc", options: ModelOptions = ModelOptions(),
                     rates: LoopRates = LoopRates()) -> tuple[dict, dict]:
    """Run platform poses ``path`` (``(N, 5)``, one per position period) on the default-geometry machine.

    Returns ``(result, trace)``: the metrics (see ``pusupu sim --plant mjx``) and arrays for
    plots (``t``, ``reference``, ``platform`` positions [m]).
    """
    if mode not in MACHINE_MODES:
        raise ValueError(f"mode: expected one of {MACHINE_MODES} (hybrid is not implemented yet), got {mode!r}")
    validate(servo)
    geom = Geometry.default()
    kinematics.check_poses(geom, path)
    rates = machine_rates(options, rates)
    plant = _plant(options)
    s_home = kinematics.inverse_kinematics(geom, jnp.asarray(geom.home))
    s_ref = np.asarray(kinematics.inverse_kinematics(geom, jnp.asarray(path)) - s_home)
    r = np.asarray(screw_ratio(servo))
    t0 = time.perf_counter()
    trace = jax.block_until_ready(_runner(plant, rates, mode)(servo, reference=jnp.asarray(s_ref / r)))
    wall = time.perf_counter() - t0
    platform = np.asarray(trace.observation["platform_pos"])
    e_platform = np.linalg.norm(platform - np.asarray(path)[:, :3], axis=1)
    e_branch = np.asarray(trace.position) - s_ref
    torque = np.asarray(trace.torque)
    rho = metrics.synchronous_error(jnp.asarray(e_branch), rates.dt_position)
    residual = np.asarray(trace.observation["closure_residual"])
    result = {
        "mode": mode, "kin_error_seed": options.kin_error_seed, "duration_s": len(path) * rates.dt_position,
        "rms_tracking_error_mm": float(np.sqrt(np.mean(e_platform**2)) * 1e3),
        "max_tracking_error_mm": float(e_platform.max() * 1e3),
        "branch_rms_error_mm": (np.sqrt(np.mean(e_branch**2, axis=0)) * 1e3).tolist(),
        "motor_torque_peak_nm": np.abs(torque).max(axis=0).tolist(),
        "branch_force_peak_n": (np.abs(torque) * np.asarray(servo.eta) / r).max(axis=0).tolist(),
        "sync_error_rho": float(rho[-1]) * 1e3,  # mm s
        "loop_closure_residual_max_mm": float(residual.max() * 1e3),
        "wall_s": wall,
    }
    return result, {"t": np.asarray(trace.t), "reference": np.asarray(path)[:, :3], "platform": platform}
