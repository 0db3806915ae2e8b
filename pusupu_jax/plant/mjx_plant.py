"""The 6PUS-UPU mechanism in MJX behind the plant interface of :mod:`pusupu_jax.plant`.

The mechanical step is the MuJoCo timestep (``ModelOptions.timestep``) and must equal
``rates.dt_mech``; the current loop and the electrical model tick ``rates.n_mech`` times
inside it.  Measurements are encoder-like: the motor angle and speed follow from the
slider through the screw, ``theta = (s - s_home) / r``, ``omega = s' / r``
(``r = lead / 2 pi``), zeroed at the home pose as a homed drive is.  ``slider`` returns
the travel from home [m] and the slider velocity [m/s].

Each slide joint carries the motor's force ``eta tau / r`` [N] and the drive train's friction
``-slider_friction(v)`` of :mod:`pusupu_jax.plant.friction` (``ServoParams`` fields ``coulomb``,
``viscous``, ``v_coulomb``), both held over the mechanical step, the friction taken at the slider
speeds at its start.  The friction's parameters are arrays of the rollout (changing them does not
recompile; a batch of servo parameters vmaps over them).

The plant is hashed by identity (it is a static argument of the jitted rollout): build it
once with :meth:`MJXPlant.create` and reuse it, or every call compiles anew.

Scenarios (seeded kinematic errors, payloads: mass, centre of mass, inertia) of the same
mechanism differ only in array fields of the model, so they can share one compiled rollout and
be vmapped: pass :meth:`MJXPlant.variant` models (stacked for a batch) as the rollout's
``plant_params``; ``None`` runs the plant's own model.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

with contextlib.redirect_stdout(io.StringIO()):  # MJX prints its optional GPU backends' import failures
    from mujoco import mjx

from ..programs import describe
from .axis import screw_ratio
from .friction import Friction, slider_friction
from .geometry import Geometry
from .model import ModelOptions, build_model, loop_closure_residual, slide_dofs, slide_qpos

if TYPE_CHECKING:
    from ..params import ServoParams


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class MJXAux:
    model: Any  # mjx.Model with the servo-dependent armature
    force_gain: Any  # (6,) N per N m: eta / r
    r: Any  # (6,) m/rad
    friction: Friction  # the drive train's, at the slider: (6,) each


@dataclass(frozen=True, eq=False)
class MJXPlant:
    """Six actuated PUS branches and the passive UPU branch, stepped by ``mjx.step``."""

    mj_model: mujoco.MjModel
    mjx_model: Any
    options: ModelOptions
    n_axes: int = 6

    @classmethod
    def create(cls, geom: Geometry | None = None, options: ModelOptions = ModelOptions()) -> "MJXPlant":
        m = build_model(geom, options)
        return cls(m, mjx.put_model(m), options)

    def key(self) -> str:
        """A stable description of all that the traced functions read from this plant: its options, its C model (as
        MuJoCo's binary MJB) and its MJX model, for the names of the traced programs kept on disk
        (:mod:`pusupu_jax.programs`)."""
        mjb = np.zeros(mujoco.mj_sizeModel(self.mj_model), np.uint8)
        mujoco.mj_saveModel(self.mj_model, None, mjb)
        return describe((type(self), self.options, self.n_axes, mjb, self.mjx_model))

    def variant(self, options: ModelOptions, geom: Geometry | None = None) -> mjx.Model:
        """The ``mjx.Model`` of the machine built with ``options``, as array fields on this plant's structure.

        Only array fields are taken from the variant (body poses, masses, inertias, geoms,
        connect anchors, ``qpos0``); the rest (sizes, indices, solver options) must be and
        are the same (a payload is the ``payload`` body welded to the platform, there and
        massless without one).  Two things are left at this plant's values: the model
        statistics (``stat``: they scale the solver's termination test, which one Newton
        iteration never reaches) and the height-field bounding radii (no height fields here).
        """
        other = mjx.put_model(build_model(geom, options))
        sizes = ("nq", "nv", "nbody", "neq", "ngeom")
        if [getattr(other, n) for n in sizes] != [getattr(self.mjx_model, n) for n in sizes]:
            raise ValueError(
                f"MJXPlant.variant: expected the sizes {sizes} of this plant's model "
                f"{[getattr(self.mjx_model, n) for n in sizes]}, got {[getattr(other, n) for n in sizes]}"
            )
        arrays = {
            f.name: getattr(other, f.name)
            for f in dataclasses.fields(other)
            if isinstance(getattr(other, f.name), jax.Array)
        }
        return self.mjx_model.replace(**arrays)

    def with_masses(self, model: mjx.Model, body_mass: jax.Array, body_pos: jax.Array) -> mjx.Model:
        """``model`` with new body masses [kg] and positions [m] (``(nbody,)``, ``(nbody, 3)``), and the constants
        MuJoCo's compiler derives from them computed again (its ``mj_setConst``, in JAX, so differentiable).

        The derived constants, at ``qpos0`` with ``model``'s armature: ``body_subtreemass`` (the mass of each body's
        subtree), ``dof_M0`` (the joint-space inertia's diagonal), ``body_invweight0`` (each body's inverse
        translational and rotational inertia at its centre of mass, ``J M^-1 J^T``'s diagonal averaged over x, y, z)
        and ``dof_invweight0`` (``M^-1``'s diagonal, averaged over a ball joint's three DOFs).  The last two set the
        regularisation of the loop-closure constraints, and so how the closed chain moves: setting only the masses
        leaves the machine a payload's inverse weights with another payload (3 against 5 kg: 10-12 % apart).
        """
        m = self.mj_model
        model = model.replace(body_mass=body_mass, body_pos=body_pos)
        data = mjx.crb(model, mjx.com_pos(model, mjx.kinematics(model, mjx.make_data(model))))  # at qpos0
        inertia = mjx.full_m(model, data)
        inverse = jnp.linalg.inv(inertia)
        subtree = [body_mass[i] for i in range(m.nbody)]
        for i in range(m.nbody - 1, 0, -1):
            subtree[m.body_parentid[i]] = subtree[m.body_parentid[i]] + subtree[i]
        weights = [jnp.zeros(2)]
        for i in range(1, m.nbody):
            if m.body_weldid[i] == 0:  # fixed to the world
                weights.append(jnp.zeros(2))
            elif m.body_simple[i] == 2:  # slides only: its mass
                weights.append(jnp.stack([1.0 / jnp.maximum(body_mass[i], mujoco.mjMINVAL), 0.0]))
            else:
                jacp, jacr = mjx.jac(model, data, data.xipos[i], i)
                weights.append(
                    jnp.stack([jnp.trace(j.T @ inverse @ j) / 3.0 for j in (jacp, jacr)])  # (nv, 3) each
                )
        dof_weights = jnp.diagonal(inverse)
        for j in range(m.njnt):
            adr, body = m.jnt_dofadr[j], m.jnt_bodyid[j]
            if m.body_simple[body] == 2:
                dof_weights = dof_weights.at[adr].set(1.0 / jnp.maximum(body_mass[body], mujoco.mjMINVAL))
            elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
                dof_weights = dof_weights.at[adr : adr + 3].set(dof_weights[adr : adr + 3].mean())
            elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                for start in (adr, adr + 3):
                    dof_weights = dof_weights.at[start : start + 3].set(dof_weights[start : start + 3].mean())
        return model.replace(
            body_subtreemass=jnp.stack(subtree),
            dof_M0=jnp.diagonal(inertia),
            body_invweight0=jnp.stack(weights),
            dof_invweight0=dof_weights,
        )

    @property
    def _dofs(self) -> np.ndarray:
        return slide_dofs(self.mj_model)

    def _connect_jacobian(self, model: mjx.Model, data: mjx.Data) -> jax.Array:
        """``(18, nv)``: d(anchor on the rod - anchor on the platform)/d(qvel) of the six spherical joints.

        MuJoCo's point Jacobian (``mj_jac``; ``mjx.jac`` with its body-tree mask built here once
        from the static tree): ``cdof[3:] + cdof[:3] x (point - subtree_com[root])`` over the
        DOFs that move the body.  ``data`` must hold ``cdof`` and ``subtree_com`` (after ``mjx.forward``).
        """
        m = self.mj_model
        xmat = data.xmat.reshape(-1, 3, 3)
        rows = []
        for k in range(6):
            eq = m.equality(f"sphere_{k}").id
            anchors = model.eq_data[eq]
            jacobians = []
            for body, anchor in ((m.eq_obj1id[eq], anchors[0:3]), (m.eq_obj2id[eq], anchors[3:6])):
                point = data.xpos[body] + xmat[body] @ anchor
                offset = point - data.subtree_com[m.body_rootid[body]]
                jacp = data.cdof[:, 3:] + jnp.cross(data.cdof[:, :3], offset)
                jacobians.append(jacp * self._moves(body)[:, None])
            rows.append((jacobians[0] - jacobians[1]).T)
        return jnp.concatenate(rows)

    def _moves(self, body: int) -> np.ndarray:
        """``(nv,)`` bool: the DOFs whose motion moves ``body`` (its own and its ancestors')."""
        m, chain = self.mj_model, set()
        while body > 0:
            chain.add(body)
            body = m.body_parentid[body]
        return np.isin(m.dof_bodyid, sorted(chain))

    @property
    def _upu_and_branch_dofs(self) -> tuple[np.ndarray, np.ndarray]:
        """DOF indices of the UPU leg's five joints (the platform's coordinates) and of the branches' 18."""
        m = self.mj_model
        upu = [m.jnt_dofadr[m.joint(name).id] for name in ("upu_phi1", "upu_phi2", "upu_leg", "upu_alpha", "upu_beta")]
        return np.array(upu), np.array(sorted(set(range(m.nv)) - set(upu)))

    @property
    def _qpos(self) -> np.ndarray:
        return slide_qpos(self.mj_model)

    def prepare(self, servo: ServoParams, plant_params: mjx.Model | None, dt: float) -> MJXAux:
        if not np.isclose(dt, self.options.timestep, rtol=1e-9):
            raise ValueError(
                f"MJXPlant: the mechanical step rates.dt_mech = {dt} s must equal the model "
                f"timestep {self.options.timestep} s"
            )
        model = self.mjx_model if plant_params is None else plant_params
        r = screw_ratio(servo)
        armature = model.dof_armature.at[self._dofs].set(servo.eta * servo.J / r**2)
        return MJXAux(model.replace(dof_armature=armature), servo.eta / r, r, Friction.of(servo))

    def init(self, aux: MJXAux) -> mjx.Data:
        """The machine at rest at its model's ``qpos0``, with what a run's start reads: the bodies' poses, centres of
        mass and bias forces (``mjx.kinematics``, ``com_pos``, ``com_vel``, ``rne``: the holding torque and the first
        record need no more), and with contacts the whole ``mjx.forward`` (the first record reads the contact forces).
        The first ``mjx.step`` computes every other field again from the state, and ``mjx.forward`` leaves the solver's
        warm start, the one computed field a step reads, as ``make_data`` left it: a run from either start is the same
        to the bit (tests/test_mjx_plant.py).  Without the constraint solver the start's program compiles in some 20 %
        less time (the default machine's start of two runs: 11.7 -> 9.1 s of CPU to trace, lower and compile)."""
        model, data = aux.model, mjx.make_data(aux.model)
        if self.options.contacts:
            return mjx.forward(model, data)
        return mjx.rne(model, mjx.com_vel(model, mjx.com_pos(model, mjx.kinematics(model, data))))

    def statics(self, aux: MJXAux, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """The machine's static equilibrium in ``data`` (at rest: gravity only), ``(J, Q)``: the five equations
        ``J^T F = Q`` for the slider forces ``F`` [N] along the motions the closed chain allows (``N``: a basis of
        those motions; ``J = N`` at the slides, ``(6, 5)``; ``Q = N^T qfrc_bias``, ``(5,)``).

        ``N``: the UPU leg's five joints are the platform's coordinates, and the spherical joints' constraints
        ``Jc_u dq_u + Jc_b dq_b = 0`` give each branch's three joints from them (``Jc_b`` is block diagonal, 3 x 3 per
        branch, invertible away from singular poses).  This is the machine's own model (seeded errors and payload
        included), and the derivatives with respect to it flow through: a run starts holding its machine, so the
        identification's derivative of a run by a payload's mass includes the change of the torque that holds it.
        """
        model = aux.model
        upu, branches = self._upu_and_branch_dofs
        jc = self._connect_jacobian(model, data)  # (18, nv)
        basis = jnp.zeros((jc.shape[1], len(upu))).at[upu].set(jnp.eye(len(upu)))
        basis = basis.at[branches].set(-jnp.linalg.solve(jc[:, branches], jc[:, upu]))
        return basis[self._dofs], basis.T @ data.qfrc_bias

    def holding_torque(
        self, aux: MJXAux, statics: tuple[jax.Array, jax.Array], force_axis: int | None = None, force: Any = None
    ) -> jax.Array:
        """Motor torques [N m] that hold the machine still, ``(6,)``, from its :meth:`statics` ``(J, Q)``: ``J^T F =
        Q`` solved for the slider forces ``F`` with the minimum norm (no internal force), as
        :mod:`pusupu_jax.plant.dynamics` distributes the inverse dynamics; with ``force_axis``, that branch pushes
        ``force`` [N] and the other five carry the rest (unique).
        """
        J, Q = statics
        if force_axis is None:
            F = J @ jnp.linalg.solve(J.T @ J, Q)
        else:
            rest = np.array([k for k in range(self.n_axes) if k != force_axis])
            F = (
                jnp.zeros(self.n_axes)
                .at[force_axis]
                .set(force)
                .at[rest]
                .set(jnp.linalg.solve(J[rest].T, Q - J[force_axis] * force))
            )
        return cast(jax.Array, F / aux.force_gain)  # a JAX array; the aux's fields are typed Any

    def measure(self, aux: MJXAux, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        s, v = self.slider(aux, data)
        return s / aux.r, v / aux.r

    def step(self, aux: MJXAux, data: mjx.Data, torque: jax.Array) -> mjx.Data:
        """One mechanical step under motor torques ``torque`` [N m] ``(6,)``, held, with the drive train's friction."""
        force = aux.force_gain * torque - slider_friction(aux.friction, data.qvel[self._dofs])
        qfrc = jnp.zeros_like(data.qfrc_applied).at[self._dofs].set(force)
        return mjx.step(aux.model, data.replace(qfrc_applied=qfrc))

    def slider(self, aux: MJXAux, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        return data.qpos[self._qpos] - aux.model.qpos0[self._qpos], data.qvel[self._dofs]

    def observe(self, aux: MJXAux, data: mjx.Data) -> dict[str, jax.Array]:
        """Platform position [m] and orientation (3x3), and the loop-closure residual [m].

        With contacts, also ``contact_force``: the force [N] (world axes) that the scene
        exerts on the tool, summed over its contacts, as an ideal wrist force sensor reads it
        (:meth:`contact_force`).
        """
        body = self.mj_model.body("platform").id
        out = {
            "platform_pos": data.xpos[body],
            "platform_mat": data.xmat[body].reshape(3, 3),
            "closure_residual": loop_closure_residual(self.mj_model, data.xpos, data.xmat, aux.model.eq_data),
        }
        if self.options.contacts:
            out["contact_force"] = self.contact_force(aux.model, data)
        return out

    def contact_force(self, model: mjx.Model, data: mjx.Data) -> jax.Array:
        """Force [N] (world axes) on the tool from every contact, ``(3,)``; zero where none is active.

        Each contact's force in its frame (normal, two tangents) comes from MJX's decoding of
        the pyramidal constraint forces (``mj_contactForce``'s); its frame's rows turn it into
        world axes.  MuJoCo's force acts on the contact's second geom along the normal, which
        points from the first geom to the second; contacts whose first geom is the tool count
        negated.  Every geom that collides is the tool or part of the scene, so each contact
        involves the tool.  Every geom of the scenes has MuJoCo's default ``condim`` 3, the only
        dimension summed here.
        """
        try:  # MJX's own decoding of mj_contactForce, for every contact of one dimension (not public API)
            from mujoco.mjx._src.support import contact_force_dim

            contact = data._impl.contact
        except (ImportError, AttributeError) as e:
            raise RuntimeError(
                f"MJXPlant.contact_force: needs MJX's JAX implementation with "
                f"mujoco.mjx._src.support.contact_force_dim and Data._impl.contact "
                f"(tested with mujoco-mjx 3.17): {e}"
            ) from None
        tool = self.mj_model.geom("tool").id
        if contact.dim.size == 0:
            return jnp.zeros(3)
        force, index = contact_force_dim(model, data, 3)
        world = jnp.einsum("ci,cij->cj", force[:, :3], contact.frame[index])
        sign = jnp.where(contact.geom[index, 0] == tool, -1.0, 1.0)
        return jnp.sum(sign[:, None] * world, axis=0)
