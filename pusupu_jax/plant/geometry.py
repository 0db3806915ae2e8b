"""Geometry of the 6PUS-UPU manipulator (host-side: defaults, YAML, validation).

No geometry is published; the default is chosen (see ``docs/geometry.md``) so that the
paper's paths (a 200 mm-radius arc in the horizontal plane and (0,0,0) -> (-100,-100,0)
-> (100,100,0) mm around the home pose) keep every slider inside its stroke with margin
and the actuation Jacobian well conditioned (checked by
``pusupu_jax.plant.kinematics.check_poses`` along both paths, in the tests).

Frames: base frame with z up; the passive UPU branch's base universal joint at the
origin; the platform frame's origin at the UPU branch's top universal joint (the
platform centre).  Branch ``i`` (PUS): a slider moves along a rail through
``rail_points[i]`` with unit direction ``rail_dirs[i]``; its position ``s_i`` [m] is
measured along the rail from ``rail_points[i]``; a rod of length ``rod_lengths[i]``
joins the slider's universal joint to the spherical joint at ``platform_points[i]``
(platform frame).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import jax
import numpy as np
import numpy.typing as npt
import yaml

from ..files import read_yaml_mapping
from ..params import ParameterError

if TYPE_CHECKING:
    import os

N_BRANCHES = 6


class GeometryError(ParameterError):
    """A geometry, pose or path is invalid (inconsistent, unreachable, out of stroke or singular)."""


def _ring(
    radius: float, centre_deg: Sequence[float], half_spread_deg: float, z: float = 0.0
) -> npt.NDArray[np.float64]:
    """Six points on a circle, in three pairs at ``centre_deg +- half_spread_deg`` (120 deg apart)."""
    ang = np.radians([c + s * half_spread_deg for c in centre_deg for s in (-1, 1)])
    return np.stack([radius * np.cos(ang), radius * np.sin(ang), np.full(6, z)], axis=1)


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Geometry:
    """Dimensions [m], masses [kg] and inertias [kg m^2] of the mechanism (all chosen)."""

    rail_points: Any  # (6, 3) m, a point of each rail (slider position 0), base frame
    rail_dirs: Any  # (6, 3) unit rail directions, base frame
    platform_points: Any  # (6, 3) m, spherical joints, platform frame
    rod_lengths: Any  # (6,) m
    stroke_min: Any  # (6,) m, slider travel limits along the rail
    stroke_max: Any  # (6,) m
    home: Any  # (5,) home pose (x, y, z [m], a, b [rad])
    upu_min: Any  # () m, shortest passive UPU leg
    upu_max: Any  # () m, longest passive UPU leg
    slider_mass: Any  # (6,) kg, carriage + ball nut
    rod_mass: Any  # (6,) kg
    platform_mass: Any  # () kg, platform + tool
    platform_inertia: Any  # (3,) kg m^2, principal, about the platform centre
    upu_mass: Any  # (2,) kg, lower and upper part of the UPU leg

    @classmethod
    def default(cls) -> "Geometry":
        """Vertical rails on a 400 mm circle, 900 mm rods, a 320 mm platform; home 800 mm above the UPU base joint.

        Chosen by a search over rail radius, spread and inclination, platform radius,
        spread and offset, rod length and home height that minimised the worst Jacobian
        condition number along the paper's paths (``docs/geometry.md``).
        """
        return cls(
            rail_points=_ring(0.40, (90.0, 210.0, 330.0), 20.0, z=-0.3),
            rail_dirs=np.tile([0.0, 0.0, 1.0], (6, 1)),
            platform_points=_ring(0.32, (90.0, 210.0, 330.0), 44.0),
            rod_lengths=np.full(6, 0.9),
            stroke_min=np.full(6, 0.0),
            stroke_max=np.full(6, 0.5),
            home=np.array([0.0, 0.0, 0.8, 0.0, 0.0]),
            upu_min=np.array(0.6),
            upu_max=np.array(1.0),
            slider_mass=np.full(6, 3.0),
            rod_mass=np.full(6, 1.2),
            platform_mass=np.array(12.0),
            platform_inertia=np.array([0.35, 0.35, 0.65]),
            upu_mass=np.array([2.0, 1.5]),
        )

    def replace(self, **changes: Any) -> "Geometry":
        return dataclasses.replace(self, **changes)


FIELDS = {  # name: (shape, unit, meaning)
    "rail_points": ((6, 3), "m", "a point of each rail (slider position 0), base frame"),
    "rail_dirs": ((6, 3), "1", "unit direction of each rail, base frame"),
    "platform_points": ((6, 3), "m", "each spherical joint, platform frame"),
    "rod_lengths": ((6,), "m", "each rod, universal to spherical joint"),
    "stroke_min": ((6,), "m", "each slider's lowest travel along its rail"),
    "stroke_max": ((6,), "m", "each slider's highest travel along its rail"),
    "home": ((5,), "m, m, m, rad, rad", "the home pose (x, y, z, a, b), where the machine starts"),
    "upu_min": ((), "m", "the passive UPU leg's shortest length"),
    "upu_max": ((), "m", "the passive UPU leg's longest length"),
    "slider_mass": ((6,), "kg", "each carriage with its ball nut"),
    "rod_mass": ((6,), "kg", "each rod"),
    "platform_mass": ((), "kg", "the platform with its fixed tooling"),
    "platform_inertia": ((3,), "kg*m^2", "the platform's principal moments about its centre"),
    "upu_mass": ((2,), "kg", "the lower and the upper tube of the UPU leg (each 400 mm, centre of mass at its middle)"),
}
_SHAPES = {name: shape for name, (shape, _, _) in FIELDS.items()}
_POSITIVE = (
    "rod_lengths",
    "upu_min",
    "upu_max",
    "slider_mass",
    "rod_mass",
    "platform_mass",
    "platform_inertia",
    "upu_mass",
)


def validate_geometry(g: Geometry) -> None:
    """Shapes, finiteness, signs and consistency; raises :class:`GeometryError` naming the field."""
    for name, shape in _SHAPES.items():
        arr = np.asarray(getattr(g, name), dtype=float)
        if arr.shape != shape:
            raise GeometryError(f"geometry.{name}: expected shape {shape}, got {arr.shape}")
        if not np.isfinite(arr).all():
            raise GeometryError(f"geometry.{name}: expected finite values, found NaN or inf")
        if name in _POSITIVE and (arr <= 0).any():
            raise GeometryError(f"geometry.{name}: expected positive values, got {arr[arr <= 0].flat[0]}")
    norms = np.linalg.norm(np.asarray(g.rail_dirs, dtype=float), axis=1)
    if not np.allclose(norms, 1.0, atol=1e-9):
        k = int(np.argmax(np.abs(norms - 1)))
        raise GeometryError(f"geometry.rail_dirs: expected unit vectors, branch {k} has length {norms[k]:.6g}")
    bad = np.nonzero(np.asarray(g.stroke_min) >= np.asarray(g.stroke_max))[0]
    if bad.size:
        raise GeometryError(
            f"geometry.stroke_min: expected < stroke_max, branch {bad[0]} has "
            f"{float(g.stroke_min[bad[0]])} >= {float(g.stroke_max[bad[0]])}"
        )
    if float(g.upu_min) >= float(g.upu_max):
        raise GeometryError(f"geometry.upu_min: expected < upu_max, got {float(g.upu_min)} >= {float(g.upu_max)}")


def load_geometry(path: str | os.PathLike[str]) -> Geometry:
    """Read a geometry YAML: any subset of the fields of :class:`Geometry`, the rest default."""
    path = Path(path)
    data = read_yaml_mapping(path, "geometry field", _SHAPES, GeometryError)
    try:
        g = Geometry.default().replace(**{k: np.asarray(v, dtype=float) for k, v in data.items()})
    except (TypeError, ValueError) as e:
        raise GeometryError(f"{path}: expected numbers ({e})") from None
    try:
        validate_geometry(g)
    except GeometryError as e:
        raise GeometryError(f"{path}: {e}") from None
    return g


def dump_geometry(g: Geometry) -> str:
    """The geometry as YAML text (every field, plain lists)."""
    text: str = yaml.safe_dump({k: np.asarray(getattr(g, k)).tolist() for k in _SHAPES}, sort_keys=False)
    return text
