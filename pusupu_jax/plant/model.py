"""The 6PUS-UPU mechanism as a MuJoCo model, built in code with ``mujoco.MjSpec`` (host-side).

Tree (23 DOF): the passive UPU branch is in the kinematic tree,
``world -> upu_lower (hinge x, hinge y) -> upu_upper (slide along the leg) -> platform
(hinge y, hinge x)``, so the platform has exactly the 5 DOF of
:mod:`pusupu_jax.plant.kinematics`; each PUS branch is its own chain,
``world -> slider_i (slide along the rail) -> rod_i (hinge x, hinge y: the universal
joint)``, closed on the platform by an equality ``connect`` at the spherical joint
(6 x 3 constraint rows, 5 DOF left).

Joint references are the home configuration, so ``qpos0`` is the assembled machine: the
slide joints read the slider travel ``s_i`` [m] and the UPU leg length [m] directly.

Each slider is driven through its ball screw: motor torque ``tau`` [N m] becomes the slider
force ``eta tau / r`` (``r = lead / 2 pi`` [m/rad]) and the rotor appears on the slide joint
as armature ``eta J / r^2`` [kg] (efficiency applied to the torque left after accelerating
the rotor; the same convention as the single-axis plant).  Those two depend on the servo
parameters and are set per rollout by the MJX plant, not here; so is the drive train's
friction (:mod:`pusupu_jax.plant.friction`), a force on each slide joint, not MuJoCo's
``frictionloss``.

The payload is a rigid body, ``payload``, welded to the platform (no joint): ``payload`` [kg]
at ``payload_com`` [m] (platform frame) with principal moments ``payload_inertia`` [kg m^2]
about its centre of mass, axes along the platform's.  It is always there (massless without a
payload), so machines with any payload have the same structure and differ only in array fields
(body position, mass, inertia): :meth:`~pusupu_jax.plant.mjx_plant.MJXPlant.variant`.

``kin_error_seed`` builds the *real* machine with seeded errors on the rail points, the
platform joint positions and the rod lengths (normal, ``kin_error_std`` [m]); the nominal
geometry is what inverse kinematics uses.  ``contacts=True`` adds a contact scene for the
compliance experiments (:data:`SCENES`); by default no geom collides:

* ``surface``: a tool sphere (10 mm radius) 150 mm under the platform and a 600 x 600 x 20 mm
  work surface 30 mm below it at home, tilted by ``surface_tilt`` [rad] about the world y axis
  through its centre (its height then changes by ``x tan(tilt)``);
* ``peg_in_hole``: a peg (a capsule, :data:`PEG`) under the platform over a square hole with
  45 deg chamfers (:data:`HOLE`) whose axis is ``hole_offset`` (x, y) [m] from the peg's at home.

The scene's geoms keep MuJoCo's default contact parameters (soft constraint, solref 20 ms,
pyramidal cone) except the sliding friction, ``friction`` (default MuJoCo's 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterable, cast

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import numpy.typing as npt

from .geometry import Geometry, GeometryError, validate_geometry
from .kinematics import inverse_kinematics, joint_points, upu_angles, xy_hinge_angles

if TYPE_CHECKING:
    from jax.typing import ArrayLike

GROUP_VISUAL = 1
UPU_TUBE = 0.4  # m: the length of each of the passive leg's two tubes (its lower one from the base up, its upper one
# from the platform down), their masses Geometry.upu_mass
SCENES = ("surface", "peg_in_hole")
CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}
PEG = dict(radius=0.008, top=0.12, bottom=0.18)  # m: a capsule from 120 to 180 mm under the platform centre
# m: half-width of the square hole (0.5 mm clearance on the peg), depth, chamfer width, and the hole's top
# below home (7 mm under the peg's tip)
HOLE = dict(half_width=0.0085, depth=0.03, chamfer=0.004, top=0.195)
# MuJoCo's line search along the solver's Newton direction takes up to this many iterations with contacts (their
# cone makes the constraints' cost piecewise along it).  Without contacts the only constraints are the spherical
# joints' equalities, whose cost is quadratic along any direction: the search starts at its minimum (the Newton step
# along it), and its iterations change nothing.  MJX still runs them, as a scan of conditionals whose both branches a
# batch (vmap) computes, so the model without contacts takes none: the same steps to the bit in C MuJoCo and to
# rounding in MJX (tests/test_mjx_plant.py), without the iterations' cost (what it buys: docs/benchmarks.md).
LS_ITERATIONS_CONTACTS = 4


@dataclass(frozen=True)
class ModelOptions:
    """Static options of the MuJoCo model."""

    timestep: float = 0.00025  # s, mechanical step (rates.dt_mech: n_mech = 5 at 20 kHz)
    payload: float = 0.0  # kg, the payload body welded to the platform
    payload_com: tuple[float, ...] = (0.0, 0.0, 0.0)  # m, the payload's centre of mass in the platform frame
    # kg m^2, its principal moments about its centre of mass (platform axes)
    payload_inertia: tuple[float, ...] = (0.0, 0.0, 0.0)
    kin_error_seed: int | None = None
    kin_error_std: float = 0.0005  # m
    contacts: bool = False
    scene: str = "surface"  # the contact scene when contacts=True: 'surface' or 'peg_in_hole'
    surface_tilt: float = 0.0  # rad, the work surface's tilt about the world y axis ('surface')
    hole_offset: tuple[float, ...] = (0.0, 0.0)  # m, the hole's axis from the peg's at home, x and y ('peg_in_hole')
    friction: float = 1.0  # sliding friction coefficient of the tool and the scene (MuJoCo takes the larger)
    cone: str = "pyramidal"  # MuJoCo's friction cone: 'pyramidal' or 'elliptic'
    solver_iterations: int = 1  # Newton iterations; 1 keeps reverse-mode gradients through MJX possible
    solref_timeconst: float = 0.002  # s, stiffness time constant of the spherical-joint constraints (8 timesteps)


def perturbed(geom: Geometry, seed: int, std: float) -> Geometry:
    """The geometry with seeded normal errors (std ``std`` [m]) on rail points, platform joints and rod lengths."""
    rng = np.random.default_rng(seed)
    return geom.replace(
        rail_points=np.asarray(geom.rail_points) + rng.normal(0.0, std, (6, 3)),
        platform_points=np.asarray(geom.platform_points) + rng.normal(0.0, std, (6, 3)),
        rod_lengths=np.asarray(geom.rod_lengths) + rng.normal(0.0, std, 6),
    )


def _in_frame(quat: npt.ArrayLike, vector: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """``vector`` (world or parent axes) expressed in the frame rotated by ``quat``."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, np.asarray(quat, dtype=float))
    # numpy's stubs type this product as Any
    return cast(npt.NDArray[np.float64], rot.reshape(3, 3).T @ np.asarray(vector, dtype=float))


def _frame_z_to(direction: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """A quaternion (w, x, y, z) turning the local z axis onto ``direction``."""
    quat = np.zeros(4)
    mujoco.mju_quatZ2Vec(quat, np.asarray(direction, dtype=float))
    return quat


def build_model(geom: Geometry | None = None, options: ModelOptions = ModelOptions()) -> mujoco.MjModel:
    """Compile the mechanism; ``geom`` is the nominal geometry (default :meth:`Geometry.default`)."""
    nominal = Geometry.default() if geom is None else geom
    validate_geometry(nominal)
    _check_options(options)
    real = (
        nominal if options.kin_error_seed is None else perturbed(nominal, options.kin_error_seed, options.kin_error_std)
    )
    home = np.asarray(nominal.home, dtype=float)
    s_home = np.asarray(inverse_kinematics(real, home))
    if not np.isfinite(s_home).all():
        raise GeometryError(f"geometry.home: the home pose {home.tolist()} is unreachable for this geometry")
    phi1, phi2, leg, alpha, beta = (float(v) for v in upu_angles(home))
    joints = np.asarray(joint_points(real, home))

    spec = mujoco.MjSpec()
    spec.modelname = "pusupu_6PUS_UPU"
    spec.option.timestep = options.timestep
    spec.option.iterations = options.solver_iterations
    spec.option.ls_iterations = LS_ITERATIONS_CONTACTS if options.contacts else 0
    spec.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    spec.option.cone = CONES[options.cone]
    if not options.contacts:
        spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    spec.compiler.inertiafromgeom = False
    world = spec.worldbody

    def body(
        parent: mujoco.MjsBody,
        name: str,
        pos: Iterable[float],
        quat: Iterable[float],
        mass: float,
        inertia: Iterable[float],
        com: Iterable[float] = (0.0, 0.0, 0.0),
    ) -> mujoco.MjsBody:
        """A body at ``pos``, ``quat`` in ``parent``'s frame, of ``mass`` [kg] with the principal ``inertia``
        [kg m^2] about its centre of mass at ``com`` [m] in its own frame.  ``ipos`` is always set: left undefined,
        MuJoCo's compiler copies the body's position into it, which puts the centre of mass at twice ``pos``."""
        b = parent.add_body(name=name, pos=list(pos), quat=list(quat))
        b.mass, b.inertia, b.explicitinertial = float(mass), list(inertia), True
        b.ipos, b.iquat = list(com), [1.0, 0.0, 0.0, 0.0]
        return b

    def hinge(b: mujoco.MjsBody, name: str, axis: Iterable[float], ref: float) -> None:
        b.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=list(axis), ref=float(ref))

    def visual(b: mujoco.MjsBody, fromto: Iterable[float], radius: float) -> None:
        b.add_geom(
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=list(fromto),
            size=[radius, 0, 0],
            contype=0,
            conaffinity=0,
            group=GROUP_VISUAL,
        )

    # passive UPU branch: the two hinges of each universal joint sit on one body, applied in order
    m_low, m_up = (float(v) for v in np.asarray(nominal.upu_mass))
    # each of the leg's two tubes is a slender rod of UPU_TUBE [m] with its centre of mass at its middle
    lower = body(
        world, "upu_lower", [0, 0, 0], [1, 0, 0, 0], m_low, _rod_inertia(m_low, UPU_TUBE), [0, 0, UPU_TUBE / 2]
    )
    hinge(lower, "upu_phi1", [1, 0, 0], phi1)
    hinge(lower, "upu_phi2", [0, 1, 0], phi2)
    visual(lower, [0, 0, 0, 0, 0, UPU_TUBE], 0.03)
    upper = body(
        lower, "upu_upper", [0, 0, leg], [1, 0, 0, 0], m_up, _rod_inertia(m_up, UPU_TUBE), [0, 0, -UPU_TUBE / 2]
    )
    upper.add_joint(name="upu_leg", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1], ref=leg)
    visual(upper, [0, 0, -UPU_TUBE, 0, 0, 0], 0.025)
    platform = body(
        upper, "platform", [0, 0, 0], [1, 0, 0, 0], nominal.platform_mass, np.asarray(nominal.platform_inertia)
    )
    body(platform, "payload", options.payload_com, [1, 0, 0, 0], options.payload, options.payload_inertia)  # at its com
    hinge(platform, "upu_alpha", [0, 1, 0], alpha)
    hinge(platform, "upu_beta", [1, 0, 0], beta)
    for c in np.asarray(real.platform_points):
        visual(platform, [0, 0, 0, *c], 0.02)
    if options.contacts and options.scene == "surface":
        platform.add_geom(name="tool", type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=[0, 0, -0.15], size=[0.01, 0, 0])
    elif options.contacts:
        platform.add_geom(
            name="tool",
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            size=[PEG["radius"], 0, 0],
            fromto=[0, 0, -PEG["top"], 0, 0, -PEG["bottom"]],
        )

    for i in range(6):
        u = np.asarray(real.rail_dirs[i], dtype=float)
        rail_quat = _frame_z_to(u)
        start = np.asarray(real.rail_points[i]) + s_home[i] * u
        slider = body(world, f"slider_{i}", start, rail_quat, np.asarray(nominal.slider_mass)[i], [1e-3, 1e-3, 1e-3])
        slider.add_joint(name=f"slide_{i}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1], ref=float(s_home[i]))
        # the rod frame's z axis points from the slider's U joint to the spherical joint at home
        rod_dir_local = _in_frame(rail_quat, joints[i] - start)
        length = float(np.asarray(real.rod_lengths)[i])
        rod_m = float(np.asarray(nominal.rod_mass)[i])
        rod = body(
            slider,
            f"rod_{i}",
            [0, 0, 0],
            _frame_z_to(rod_dir_local / np.linalg.norm(rod_dir_local)),
            rod_m,
            _rod_inertia(rod_m, length),
            [0, 0, length / 2],
        )
        hinge(rod, f"rod_{i}_x", [1, 0, 0], 0.0)
        hinge(rod, f"rod_{i}_y", [0, 1, 0], 0.0)
        visual(rod, [0, 0, 0, 0, 0, length], 0.012)
        eq = spec.add_equality(
            name=f"sphere_{i}",
            type=mujoco.mjtEq.mjEQ_CONNECT,
            objtype=mujoco.mjtObj.mjOBJ_BODY,
            name1=f"rod_{i}",
            name2="platform",
        )
        eq.data[0:3] = [0, 0, length]
        eq.solref = [options.solref_timeconst, 1.0]
        eq.solimp = [0.99, 0.999, 0.001, 0.5, 2.0]
    if options.contacts and options.scene == "surface":
        tilt = float(options.surface_tilt)
        world.add_geom(
            name="surface",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[0, 0, float(home[2]) - 0.2],
            size=[0.3, 0.3, 0.01],
            quat=[np.cos(tilt / 2), 0, -np.sin(tilt / 2), 0],
        )
    elif options.contacts:
        _add_hole(
            world, np.asarray(home[:2]) + np.asarray(options.hole_offset, dtype=float), float(home[2]) - HOLE["top"]
        )
    for body_geom in spec.geoms:
        if body_geom.contype:
            body_geom.friction = [float(options.friction), *list(body_geom.friction)[1:]]
    return spec.compile()


def _add_hole(world: mujoco.MjsBody, centre: npt.NDArray[np.float64], top: float) -> None:
    """The square hole of :data:`HOLE` around ``centre`` (x, y) [m], its top at height ``top`` [m].

    Each side is three boxes: a 40 mm-thick wall up to the chamfer's foot (``chamfer`` below the top),
    a wall set back by ``chamfer`` from the hole's edge that reaches the top, and between them a
    2 mm-thick box at 45 deg whose upper face runs from the hole's edge at the chamfer's foot out
    to the top (the chamfer).
    """
    w, d, c, t, e = HOLE["half_width"], HOLE["depth"], HOLE["chamfer"], 0.02, 0.001
    for k, (ax, sign) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1))):
        normal = np.eye(3)[ax] * sign  # from the hole's axis out through this side
        span = np.abs(np.eye(3)[1 - ax]) * (w + 2 * t + c)  # half-length along the side, past the corners
        lower = np.array([*centre, top - c - (d - c) / 2]) + normal * (w + t)
        world.add_geom(
            name=f"hole_wall_{k}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=list(lower),
            size=list(np.abs(normal) * t + span + np.array([0, 0, (d - c) / 2])),
        )
        upper = np.array([*centre, top - c / 2]) + normal * (w + c + (2 * t - c) / 2)
        world.add_geom(
            name=f"hole_rim_{k}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=list(upper),
            size=list(np.abs(normal) * (2 * t - c) / 2 + span + np.array([0, 0, c / 2])),
        )
        inward_up = (-normal + np.array([0, 0, 1])) / np.sqrt(2)
        quat = np.zeros(4)
        mujoco.mju_quatZ2Vec(quat, inward_up)  # the box's z along the chamfer face's normal
        frame = np.zeros(9)
        mujoco.mju_quat2Mat(frame, quat)
        along_x = abs(frame.reshape(3, 3)[:, 0] @ np.abs(np.eye(3)[1 - ax])) > 0.5  # the box's x lies along the side
        half_across, half_along = c / np.sqrt(2), w + c
        middle = np.array([*centre, top - c / 2]) + normal * (w + c / 2)
        world.add_geom(
            name=f"hole_chamfer_{k}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=list(middle - inward_up * e),
            quat=list(quat),
            size=[half_along, half_across, e] if along_x else [half_across, half_along, e],
        )


def _check_options(options: ModelOptions) -> None:
    """One-line ValueError for a payload or contact option out of its domain."""
    _check_payload(options)
    if options.scene not in SCENES:
        raise ValueError(f"ModelOptions.scene: expected one of {SCENES}, got {options.scene!r}")
    if options.cone not in CONES:
        raise ValueError(f"ModelOptions.cone: expected one of {tuple(CONES)}, got {options.cone!r}")
    if not (np.isfinite(options.friction) and options.friction >= 0):
        raise ValueError(f"ModelOptions.friction: expected a finite number >= 0, got {options.friction!r}")
    if not (np.isfinite(options.surface_tilt) and abs(options.surface_tilt) < 0.5):
        raise ValueError(
            f"ModelOptions.surface_tilt: expected a finite angle under 0.5 rad, got {options.surface_tilt!r}"
        )
    offset = np.asarray(options.hole_offset, dtype=float)
    if offset.shape != (2,) or not np.isfinite(offset).all() or np.abs(offset).max() > 0.02:
        raise ValueError(f"ModelOptions.hole_offset: expected (x, y) within 20 mm [m], got {options.hole_offset!r}")


def _check_payload(options: ModelOptions) -> None:
    """One-line ValueError for a payload that is no rigid body: mass finite and >= 0, centre of mass finite, principal
    moments finite, >= 0 and satisfying the triangle inequality (each at most the sum of the other two); no moments
    without mass."""
    mass = options.payload
    if not (np.isfinite(mass) and mass >= 0):
        raise ValueError(f"ModelOptions.payload: expected a finite mass >= 0 [kg], got {mass!r}")
    com = np.asarray(options.payload_com, dtype=float)
    if com.shape != (3,) or not np.isfinite(com).all():
        raise ValueError(
            f"ModelOptions.payload_com: expected a finite (x, y, z) [m] in the platform frame, got "
            f"{options.payload_com!r}"
        )
    inertia = np.asarray(options.payload_inertia, dtype=float)
    if inertia.shape != (3,) or not np.isfinite(inertia).all() or (inertia < 0).any():
        raise ValueError(
            f"ModelOptions.payload_inertia: expected three finite principal moments >= 0 [kg m^2], got "
            f"{options.payload_inertia!r}"
        )
    if mass == 0 and inertia.any():
        raise ValueError(
            f"ModelOptions.payload_inertia: expected (0, 0, 0) without a payload mass (payload 0 kg), got "
            f"{options.payload_inertia!r}"
        )
    if (2 * inertia > inertia.sum()).any():
        raise ValueError(
            f"ModelOptions.payload_inertia: expected principal moments of a rigid body (each at most the "
            f"sum of the other two), got {options.payload_inertia!r}"
        )


def _rod_inertia(mass: float, length: float) -> list[float]:
    """Principal inertia [kg m^2] of a slender rod about its centre, axis along z."""
    transverse = mass * length**2 / 12.0
    return [transverse, transverse, 1e-3 * mass]


def slide_dofs(model: mujoco.MjModel) -> np.ndarray:
    """DOF indices of the six actuated slide joints, in branch order."""
    return np.array([model.jnt_dofadr[model.joint(f"slide_{i}").id] for i in range(6)])


def slide_qpos(model: mujoco.MjModel) -> np.ndarray:
    """qpos indices of the six slide joints, in branch order."""
    return np.array([model.jnt_qposadr[model.joint(f"slide_{i}").id] for i in range(6)])


def connect_gap(model: mujoco.MjModel, xpos: ArrayLike, xmat: ArrayLike, eq_data: ArrayLike | None = None) -> jax.Array:
    """Anchor on the rod minus anchor on the platform [m] of the six spherical-joint ``connect`` constraints.

    ``xpos (..., nbody, 3)`` and ``xmat (..., nbody, 9 or 3x3)`` are body poses from
    ``MjData`` or MJX ``Data`` (traced or not); the result is ``(..., 6, 3)``.
    ``eq_data`` (default ``model.eq_data``) holds the anchors, for a model variant.
    """
    xpos = jnp.asarray(xpos)
    xmat = jnp.asarray(xmat).reshape(xpos.shape[:-1] + (3, 3))
    eqs = [model.equality(f"sphere_{i}").id for i in range(6)]
    b1, b2 = model.eq_obj1id[eqs], model.eq_obj2id[eqs]
    data = jnp.asarray(model.eq_data if eq_data is None else eq_data)[jnp.asarray(eqs)]
    p1 = xpos[..., b1, :] + jnp.einsum("...kij,kj->...ki", xmat[..., b1, :, :], data[:, 0:3])
    p2 = xpos[..., b2, :] + jnp.einsum("...kij,kj->...ki", xmat[..., b2, :, :], data[:, 3:6])
    return p1 - p2


def loop_closure_residual(
    model: mujoco.MjModel, xpos: ArrayLike, xmat: ArrayLike, eq_data: ArrayLike | None = None
) -> jax.Array:
    """Largest distance [m] between the two anchors of the six spherical-joint constraints (:func:`connect_gap`)."""
    return jnp.max(jnp.linalg.norm(connect_gap(model, xpos, xmat, eq_data), axis=-1), axis=-1)


def pose_to_qpos(model: mujoco.MjModel, real: Geometry) -> Callable[[ArrayLike], jax.Array]:
    """A JAX function ``q (..., 5) -> qpos (..., nq)`` putting the machine ``real`` at pose ``q``, every constraint
    closed.

    Differentiable: its Jacobian ``d qpos / d q`` maps pose rates to joint velocities (every
    joint is a hinge or a slide, so ``qvel`` is the time derivative of ``qpos``).
    """
    index = {
        name: int(model.jnt_qposadr[model.joint(name).id])
        for name in ("upu_phi1", "upu_phi2", "upu_leg", "upu_alpha", "upu_beta")
    }
    upu = jnp.array(list(index.values()))
    branch = [
        jnp.array([int(model.jnt_qposadr[model.joint(f"{j}_{i}{k}").id]) for i in range(6)])
        for j, k in (("slide", ""), ("rod", "_x"), ("rod", "_y"))
    ]

    def frames(kind: str) -> jax.Array:
        out = np.zeros((6, 9))
        for i in range(6):
            mujoco.mju_quat2Mat(out[i], model.body_quat[model.body(f"{kind}_{i}").id])
        return jnp.asarray(out.reshape(6, 3, 3))

    slider_rot, rod_rot = frames("slider"), frames("rod")
    qpos0 = jnp.asarray(model.qpos0)
    rail_points, rail_dirs = jnp.asarray(real.rail_points), jnp.asarray(real.rail_dirs)

    def one(q: jax.Array) -> jax.Array:
        s = inverse_kinematics(real, q)
        rod = joint_points(real, q) - (rail_points + s[:, None] * rail_dirs)
        rod = jnp.einsum("kji,kj->ki", rod_rot, jnp.einsum("kji,kj->ki", slider_rot, rod))  # in each rod's frame
        ax, ay = xy_hinge_angles(rod)
        return (
            qpos0.at[upu].set(jnp.stack(upu_angles(q))).at[branch[0]].set(s).at[branch[1]].set(ax).at[branch[2]].set(ay)
        )

    return jnp.vectorize(one, signature="(5)->(n)")


def assembled_qpos(model: mujoco.MjModel, real: Geometry, q: npt.ArrayLike) -> np.ndarray:
    """``qpos`` that puts the machine described by ``real`` at pose ``q`` with every constraint closed."""
    return np.asarray(pose_to_qpos(model, real)(jnp.asarray(q, dtype=float)))
