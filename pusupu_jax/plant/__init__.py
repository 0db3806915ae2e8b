"""Plants behind one interface, so the cascade runs the same against any of them.

A plant is a hashable object (a static argument of the jitted rollout) with:

* ``key() -> str``: a stable description of all that the traced functions read from the plant, for the
  names of the traced programs kept on disk (:mod:`pusupu_jax.programs`);

* ``n_axes`` (int): number of driven axes;
* ``prepare(servo, plant_params, dt) -> aux``: everything the step needs that depends
  only on parameters (e.g. the ZOH matrices), computed once per rollout outside the
  scan; ``dt`` [s] is the mechanical step;
* ``init(aux) -> state``: the machine at rest at its home position;
* ``statics(aux, state) -> statics``: the plant's static equilibrium in ``state``, what the
  holding torques are solved from;
* ``holding_torque(aux, statics, force_axis=None, force=None) -> torque``: the motor torques
  [N m] that hold the plant still (its static equilibrium), optionally with one axis pushing a
  given slider force [N]; runs start from it (:func:`pusupu_jax.sim.rollout`);
* ``measure(aux, state) -> (theta, omega)``: the encoders, motor angle [rad] and
  speed [rad/s], shape ``(..., n_axes)``;
* ``step(aux, state, torque) -> state``: advance one mechanical step with motor
  torques [N m] held;
* ``slider(aux, state) -> (x, v)``: slider position [m] and velocity [m/s];
* ``observe(aux, state) -> pytree``: what the trace keeps of the plant at each outer
  step (the full state of a large plant would not fit in memory over long runs).
"""

from typing import TYPE_CHECKING, Any, NamedTuple

from .axis import AxisPlant


class PlantDrives(NamedTuple):
    """A plant's parameters with drive values of the machine's own, where the machine differs from its machine file
    (a machine drawn about an identified one, :mod:`pusupu_jax.machine_draws`).

    ``params``: what a plant's ``prepare`` takes as ``plant_params`` (an MJX model, a single-axis load).  ``drives``:
    ``{field: (n_axes,)}``, plant fields of :class:`~pusupu_jax.params.ServoParams` (friction [N], [N s/m], rotor
    inertia ``J`` [kg m^2], ``Kt`` [N m/A], ``Ke`` [V s/rad]...).  The rollout gives them to the plant, the motor and
    what each drive knows of its motor (its back-EMF feedforward); what the host computes from the machine file (the
    hybrid force law's current, ROS's PID clamp) keeps the ServoParams' values (:func:`pusupu_jax.sim.plant_side`,
    :func:`pusupu_jax.loops.on_machine`)."""

    params: Any
    drives: dict[str, Any]


if TYPE_CHECKING:
    from typing import Protocol

    import jax

    from ..params import ServoParams

    class Plant(Protocol):
        """The interface above, for type checkers; ``aux`` and the state are each plant's own."""

        def __hash__(self) -> int: ...

        def key(self) -> str: ...

        @property
        def n_axes(self) -> int: ...

        def prepare(self, servo: ServoParams, plant_params: Any, dt: float) -> Any: ...

        def init(self, aux: Any) -> Any: ...

        def statics(self, aux: Any, state: Any) -> Any: ...

        def holding_torque(
            self, aux: Any, statics: Any, force_axis: int | None = None, force: Any = None
        ) -> jax.Array: ...

        def measure(self, aux: Any, state: Any) -> tuple[jax.Array, jax.Array]: ...

        def step(self, aux: Any, state: Any, torque: jax.Array) -> Any: ...

        def slider(self, aux: Any, state: Any) -> tuple[jax.Array, jax.Array]: ...

        def observe(self, aux: Any, state: Any) -> Any: ...


__all__ = ["AxisPlant", "PlantDrives"]
