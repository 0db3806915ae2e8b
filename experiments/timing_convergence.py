"""Timing convergence of the co-simulation: every step halved, the arc's tracking error must barely move.

    python experiments/timing_convergence.py [--trajectory arc|p2p] [--mode imc|pid]

Runs the path at the default steps (20 kHz current loop, 0.25 ms MJX step, velocity and
position loops at 4 kHz and 1 kHz) and with every step halved (40 kHz, 0.125 ms, 8 kHz,
2 kHz; the constraint stiffness is a physical time constant and stays 2 ms), and prints
JSON with both results and the relative change of the platform's RMS tracking error.
"""

from __future__ import annotations

import argparse
import json
import dataclasses

from pusupu_jax.config import setup_jax


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trajectory", choices=("arc", "p2p"), default="arc")
    ap.add_argument("--mode", choices=("imc", "pid"), default="imc")
    args = ap.parse_args()
    setup_jax()
    from pusupu_jax import LoopRates, ServoParams
    from pusupu_jax.machine import simulate_machine
    from pusupu_jax.plant.geometry import Geometry
    from pusupu_jax.plant.model import ModelOptions
    from pusupu_jax.trajectories import platform_path

    runs = {}
    for label, factor in (("default", 1), ("halved", 2)):
        rates = LoopRates().finer(factor)
        options = dataclasses.replace(ModelOptions(), timestep=ModelOptions().timestep / factor)
        path = platform_path(args.trajectory, Geometry.default().home, rates)
        result, _ = simulate_machine(ServoParams.table1(), path, mode=args.mode, options=options, rates=rates)
        runs[label] = {k: result[k] for k in ("rms_tracking_error_mm", "max_tracking_error_mm", "sync_error_rho",
                                              "loop_closure_residual_max_mm", "duration_s", "wall_s")}
    a, b = runs["default"]["rms_tracking_error_mm"], runs["halved"]["rms_tracking_error_mm"]
    print(json.dumps({"trajectory": args.trajectory, "mode": args.mode, "runs": runs,
                      "rms_relative_change": abs(b - a) / a}, indent=2))


if __name__ == "__main__":
    main()
