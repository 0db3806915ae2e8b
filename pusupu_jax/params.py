"""Parameters of the servo drives, the single-axis load and the loop rates.

Every physical or controller parameter is a field of a frozen dataclass registered
as a JAX pytree, one value per axis (shape ``(6,)``; leading batch dimensions are
allowed, e.g. ``(1024, 6)`` for a vmapped parameter sweep).  Changing a value never
recompiles a jitted function; changing a shape or a :class:`LoopRates` field does.

Defaults are the paper's Table 1.  What the paper leaves out is chosen here; why, in the comments of the
fields' sections and ``docs/parameters.md``.

Validation is host-side and explicit: :func:`validate` (called by
:meth:`ServoParams.from_mapping`, :func:`load_params_file` and
:func:`pusupu_jax.sim.simulate`) raises :class:`ParameterError` naming the field,
the expected value and what was found.  Constructors do not validate, because JAX
rebuilds these objects with tracers and zeros (``tree_map(zeros_like, p)``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, Sequence, TypeVar, cast

import jax
import numpy as np
import numpy.typing as npt

from . import inputs

if TYPE_CHECKING:
    from _typeshed import DataclassInstance
    from typing_extensions import Self

N_AXES = 6
IMC_FORMS = ("full", "printed")


class ParameterError(ValueError):
    """A parameter, parameter file or loop-rate setting is invalid."""


def _f(
    default: float,
    unit: str,
    doc: str,
    kind: str = "positive",
    section: str = "",
    bounds: tuple[float, float | str, str] | None = None,
) -> float:
    """A per-axis field: ``kind`` is 'positive', 'nonnegative' or 'any' (finite); ``section``: where a gain file puts
    it;
    ``bounds``: ``(low, high, why)``, the physically meaningful range and the reason for it (``high`` may name another
    field of the same class, a rating the value may not exceed)."""
    return field(
        default=default, metadata={"unit": unit, "doc": doc, "kind": kind, "section": section, "bounds": bounds}
    )


def _choice(default: str, choices: tuple[str, ...], doc: str, section: str = "") -> str:
    """A static, machine-wide field: one of ``choices`` (a jit-static pytree field: changing it recompiles)."""
    return field(
        default=default,
        metadata={"unit": "", "doc": doc, "kind": "choice", "choices": choices, "static": True, "section": section},
    )


def array_fields(cls: type[DataclassInstance]) -> list[dataclasses.Field[Any]]:
    """The per-axis (traced) fields of a parameter class."""
    return [f for f in fields(cls) if not f.metadata.get("static")]


def static_fields(cls: type[DataclassInstance]) -> list[dataclasses.Field[Any]]:
    """The static (choice) fields of a parameter class."""
    return [f for f in fields(cls) if f.metadata.get("static")]


def arrays(p: DataclassInstance) -> dict[str, Any]:
    """``{name: value}`` of the per-axis fields of a parameter set (its static choices left out)."""
    return {f.name: getattr(p, f.name) for f in array_fields(type(p))}


_D = TypeVar("_D", bound="DataclassInstance")
_P = TypeVar("_P", bound="_PerAxis")
_T = TypeVar("_T")


def _pytree(cls: type[_D]) -> type[_D]:
    return jax.tree_util.register_dataclass(
        cls, data_fields=[f.name for f in array_fields(cls)], meta_fields=[f.name for f in static_fields(cls)]
    )


class _PerAxis:
    """Constructors shared by the per-axis parameter classes."""

    if TYPE_CHECKING:  # every subclass is a dataclass
        __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]

    @classmethod
    def default(cls) -> Self:
        """Every per-axis field at its default, as float arrays of shape (6,); the static choices at theirs."""
        # every per-axis field has a default (never dataclasses.MISSING)
        return cls(**{f.name: np.full((N_AXES,), float(cast(float, f.default))) for f in array_fields(cls)})

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], base: Self | None = None) -> Self:
        """The defaults (or ``base``) with ``values`` replaced; scalars apply to every axis. Validates."""
        return _from_mapping(cls, values, base)

    def replace(self, **changes: Any) -> Self:
        return dataclasses.replace(self, **changes)

    def __repr__(self) -> str:
        """A table of every field [unit] per axis (:func:`describe`), not the arrays' reprs."""
        return describe(self)

    def _repr_markdown_(self) -> str:
        return describe(self, markdown=True)


@_pytree
@dataclass(frozen=True, repr=False)
class ServoParams(_PerAxis):
    """Servo drive of each axis: the three loops of the paper (Fig. 2) and the motor.

    Every field has shape ``(..., 6)``.  Table 1 values where the paper gives them; the rest chosen, as the
    section comments below and ``docs/parameters.md`` say.  A field's doc says what it is on any machine (it comments
    the machine files and gain files); why the default has its value is in those comments.
    """

    # --- position loop, 2-DOF IMC (eq. 9) ---
    lambda1: Any = _f(
        0.018,
        "s",
        "IMC reference (tracking) filter time parameter, C1",
        section="position",
        bounds=(
            5e-05,
            10.0,
            "a filter faster than one period of the fastest position loop (20 kHz) does nothing; one "
            "of 10 s takes a minute to follow",
        ),
    )
    lambda2: Any = _f(
        0.15,
        "s",
        "IMC feedback (robustness) filter time parameter, C1 and C2",
        section="position",
        bounds=(
            5e-05,
            10.0,
            "as lambda1: faster than one period of the fastest position loop does nothing, 10 s "
            "leaves the axis nearly uncontrolled",
        ),
    )
    T0: Any = _f(
        0.01475,
        "s",
        "time constant of the closed velocity loop as modelled by C2",
        section="position",
        bounds=(0.0001, 1.0, "a velocity loop closed faster than 0.1 ms or slower than 1 s is no servo drive's"),
    )
    # --- velocity loop (eq. 6-8) ---
    Kv: Any = _f(
        0.015,
        "A/(rad/s)",
        "velocity PI proportional gain",
        section="velocity",
        bounds=(
            1e-05,
            10.0,
            "10 A per rad/s spends the whole 10 A current limit on 1 rad/s (10 rpm) of speed "
            "error; 1e-5 A per rad/s leaves the axis uncontrolled",
        ),
    )
    Tv: Any = _f(
        5.0,
        "s",
        "velocity PI integral time",
        section="velocity",
        bounds=(
            0.0001,
            100.0,
            "an integral time beyond 100 s is no integral action; below 0.1 ms it is faster than the velocity loop",
        ),
    )
    Kw: Any = _f(
        1.0,
        "1",
        "velocity feedback filter gain",
        section="velocity",
        bounds=(0.5, 2.0, "a calibration factor of the speed measurement: beyond a factor 2 it is a wrong unit"),
    )
    Tw: Any = _f(
        0.01,
        "s",
        "velocity feedback and reference filter time constant",
        section="velocity",
        bounds=(1e-06, 0.1, "a speed filter slower than 0.1 s is slower than any velocity loop it serves"),
    )
    # --- current loop (eq. 1-5) ---
    Ki: Any = _f(
        1.0,
        "V/A",
        "current PI proportional gain (command volts per amp, before the inverter gain Kn)",
        section="current",
        bounds=(
            0.001,
            1000.0,
            "1 kV per amp of current error saturates any inverter on a milliamp; 1 mV per amp "
            "leaves the current uncontrolled",
        ),
    )
    Ti: Any = _f(
        0.00208,
        "s",
        "current PI integral time (= L/R in the paper)",
        section="current",
        bounds=(1e-06, 1.0, "an electrical time constant L/R is microseconds to a fraction of a second"),
    )
    Kcf: Any = _f(
        1.0,
        "1",
        "current feedback filter gain",
        section="current",
        bounds=(0.5, 2.0, "a calibration factor of the current measurement: beyond a factor 2 it is a wrong unit"),
    )
    Tcf: Any = _f(
        0.00016,
        "s",
        "current feedback and reference filter time constant",
        section="current",
        bounds=(1e-07, 0.01, "a current filter slower than 10 ms is slower than any current loop it serves"),
    )
    Kn: Any = _f(
        4.43,
        "1",
        "inverter (SPWM) gain",
        section="plant",
        bounds=(0.1, 1000.0, "an inverter gain, volts out per volt of command"),
    )
    Tn: Any = _f(
        0.0001,
        "s",
        "inverter time constant",
        section="plant",
        bounds=(1e-07, 0.01, "an inverter responds within microseconds to milliseconds"),
    )
    R: Any = _f(
        1.3,
        "ohm",
        "armature resistance",
        section="plant",
        bounds=(0.001, 1000.0, "armature resistances of servo motors: milliohms to hundreds of ohms"),
    )
    L: Any = _f(
        0.0027,
        "H",
        "armature inductance",
        section="plant",
        bounds=(1e-06, 1.0, "armature inductances of servo motors: microhenries to a henry"),
    )
    # --- motor (J from Table 1; the rest chosen, docs/parameters.md: Kt solved so that the velocity loop identified
    # from the model has T0 = 0.01475 s with the default AxisLoad, analysis.kt_for_T0; 3000 rpm; a 10 A, 310 V drive;
    # 13 N m peak torque at I_max; V_max the bus less a margin) ---
    J: Any = _f(
        0.000188,
        "kg*m^2",
        "motor rotor inertia",
        section="plant",
        bounds=(1e-07, 1.0, "rotor inertias of servo motors: 0.1 g cm^2 to 1 kg m^2"),
    )
    Kt: Any = _f(
        1.322,
        "N*m/A",
        "torque constant: motor torque per armature current",
        section="plant",
        bounds=(0.001, 100.0, "torque constants of servo motors"),
    )
    Ke: Any = _f(
        1.322,
        "V*s/rad",
        "back-EMF constant; equal to Kt (SI units, power balance of the DC-equivalent motor model)",
        section="plant",
        bounds=(0.001, 100.0, "back-EMF constants of servo motors (equal to Kt in SI units)"),
    )
    I_peak: Any = _f(
        10.0,
        "A",
        "the drive's peak current rating; I_max may not exceed it",
        section="plant",
        bounds=(0.001, 1000.0, "peak current ratings of servo drives: milliamps to a kiloamp"),
    )
    V_dc: Any = _f(
        310.0,
        "V",
        "the drive's DC bus voltage; V_max may not exceed it",
        section="plant",
        bounds=(1.0, 10000.0, "DC bus voltages of servo drives"),
    )
    speed_max: Any = _f(
        314.16,
        "rad/s",
        "the motor's rated maximum speed; a path whose motor speed exceeds it is refused",
        section="plant",
        bounds=(1.0, 20000.0, "maximum speeds of servo motors: 10 rpm to 190 000 rpm"),
    )
    emf_ff: Any = _f(
        1.0,
        "1",
        "fraction of the back-EMF Ke*w fed forward into the current PI output "
        "(decoupling, as PMSM drives do; 1 = full, 0 = none)",
        kind="nonnegative",
        section="current",
        bounds=(
            0.0,
            1.0,
            "more than the whole back-EMF fed forward is positive speed feedback: from 1.7 on, Table "
            "1's current loop is unstable",
        ),
    )
    I_max: Any = _f(
        10.0,
        "A",
        "current limit on the velocity PI output",
        section="limits",
        bounds=(
            0.0,
            "I_peak",
            "the drive's peak current rating I_peak (the clamp may not exceed what the machine is rated for)",
        ),
    )
    V_max: Any = _f(
        300.0,
        "V",
        "armature voltage limit; the current PI output saturates at V_max/Kn",
        section="limits",
        bounds=(0.0, "V_dc", "the DC bus voltage V_dc (the inverter cannot apply more)"),
    )
    following_error: Any = _f(
        0.005,
        "m",
        "following-error window (CiA 402 object 0x6065), in slider travel: "
        "a branch whose position error stays beyond it for following_error_time stops the "
        "machine",
        section="limits",
        bounds=(
            1e-05,
            0.05,
            "a window under 10 um trips on encoder noise; one over 50 mm lets a branch run far off its path",
        ),
    )
    following_error_time: Any = _f(
        0.05,
        "s",
        "following-error time-out (CiA 402 object 0x6066)",
        section="limits",
        bounds=(0.001, 1.0, "under 1 ms is a single position period; over 1 s lets a runaway go on for a second"),
    )
    # --- drive train (chosen, docs/parameters.md: a 10 mm lead) ---
    lead: Any = _f(
        0.01,
        "m/rev",
        "ball-screw lead: slider travel per motor revolution",
        section="plant",
        bounds=(0.0001, 0.1, "ball-screw leads: 0.1 mm to 100 mm per revolution"),
    )
    eta: Any = _f(
        0.9,
        "1",
        "ball-screw efficiency (0 < eta <= 1); the load seen by the motor is divided by eta",
        section="plant",
        bounds=(0.001, 1.0, "an efficiency: at most 1"),
    )
    # --- drive-train friction at the slider (chosen; F = coulomb tanh(v / v_coulomb) + viscous v, opposing the
    # slider's speed v: pusupu_jax.plant.friction) ---
    coulomb: Any = _f(
        20.0,
        "N",
        "Coulomb friction of the screw and the rail at the slider (smoothed by tanh)",
        kind="nonnegative",
        section="plant",
        bounds=(0.0, 100000.0, "Coulomb friction of a rail and screw"),
    )
    viscous: Any = _f(
        50.0,
        "N*s/m",
        "viscous friction of the screw and the rail at the slider",
        kind="nonnegative",
        section="plant",
        bounds=(0.0, 1000000.0, "viscous friction of a rail and screw"),
    )
    v_coulomb: Any = _f(
        0.001,
        "m/s",
        "slider speed over which the Coulomb friction builds up (the tanh's scale)",
        section="plant",
        bounds=(1e-06, 10.0, "the speed over which Coulomb friction builds up"),
    )
    # --- baseline PID position loop (chosen: same crossover as the nominal IMC loop, see docs/parameters.md) ---
    Kp_pid: Any = _f(
        6.5,
        "1/s",
        "PID proportional gain, motor rad/s per rad of position error",
        section="pid",
        bounds=(0.0001, 1000.0, "a position gain beyond 1000 1/s puts the crossover past the velocity loop's"),
    )
    Ki_pid: Any = _f(
        8.0,
        "1/s^2",
        "PID integral gain",
        section="pid",
        bounds=(1e-06, 100000.0, "as Kp_pid: beyond 1e5 1/s^2 the integral alone crosses over past the velocity loop"),
    )
    Kd_pid: Any = _f(
        0.02,
        "1",
        "PID derivative gain",
        section="pid",
        bounds=(
            1e-08,
            10.0,
            "a derivative gain beyond 10 amplifies the encoder's noise tenfold into the speed reference",
        ),
    )
    Tf_pid: Any = _f(
        0.005,
        "s",
        "PID derivative filter time constant, Kd s/(Tf s + 1)",
        section="pid",
        bounds=(
            1e-05,
            1.0,
            "a derivative filter faster than 10 us is faster than any position loop; one of 1 s removes the derivative",
        ),
    )
    Kff_pid: Any = _f(
        1.0,
        "1",
        "velocity feedforward gain of mode pid_ff: the reference's backward difference "
        "[rad/s] times Kff is added to the PID output",
        kind="nonnegative",
        section="pid",
        bounds=(
            0.0,
            1.5,
            "1 feeds the whole reference speed forward; beyond 1.5 the feedforward alone overshoots by half",
        ),
    )
    # --- static structure (machine-wide; changing it recompiles) ---
    imc_form: str = _choice(
        "full",
        IMC_FORMS,
        "form of the 2-DOF IMC prefilter C1: 'full' (reference response "
        "(3 l1 s+1)/(l1 s+1)^3, as section 2.2 describes; docs/imc.md) or 'printed' (eq. 9 "
        "as printed, (3 l1 s+1)/(3 l2 s+1))",
        section="position",
    )

    @classmethod
    def table1(cls) -> "ServoParams":
        """The paper's Table 1 (plus the documented choices), as float arrays of shape (6,)."""
        return cls.default()


@_pytree
@dataclass(frozen=True, repr=False)
class AxisLoad(_PerAxis):
    """Load of the single-axis plant: the slider and its share of the mechanism, as a lumped mass (the drive train's
    friction is the machine's: :class:`ServoParams`).

    Every field has shape ``(..., 6)``.  All values chosen (no load is published).
    """

    mass: Any = _f(
        20.0,
        "kg",
        "lumped moving mass on the slider",
        bounds=(0.001, 10000.0, "a slider and its share of the mechanism: grams to ten tonnes"),
    )
    inclination: Any = _f(
        0.0,
        "rad",
        "rail inclination from the horizontal (pi/2: vertical, gravity pulls the slider towards negative positions)",
        kind="any",
        bounds=(-3.1416, 3.1416, "an angle from the horizontal, within half a turn either way"),
    )
    g: Any = _f(
        9.81,
        "m/s^2",
        "gravitational acceleration",
        kind="nonnegative",
        bounds=(0.0, 100.0, "gravitational acceleration: 0 (no gravity) to ten times the earth's"),
    )


@dataclass(frozen=True)
class LoopRates:
    """Loop rates (static: changing them recompiles).

    The electrical model and the current loop tick at ``f_current``; the plant's
    mechanics steps every ``n_mech`` ticks (torque averaged over them), the velocity
    loop every ``n_velocity`` ticks and the position loop every ``n_velocity *
    n_position`` ticks.  Defaults: 20 kHz, 4 kHz, 1 kHz.  ``method`` discretises the
    controllers and filters ('tustin' or 'zoh'); the physical parts are always
    sampled with a zero-order hold (exact for their linear part).
    """

    f_current: float = 20000.0  # Hz
    n_velocity: int = 5
    n_position: int = 4
    n_mech: int = 1
    method: str = "tustin"

    def __post_init__(self) -> None:
        if not (isinstance(self.f_current, (int, float)) and math.isfinite(self.f_current) and self.f_current > 0):
            raise ParameterError(f"rates.f_current: expected a positive number of Hz, got {self.f_current!r}")
        for name in ("n_velocity", "n_position", "n_mech"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
                raise ParameterError(f"rates.{name}: expected an integer >= 1, got {v!r}")
        if self.n_velocity % self.n_mech:
            raise ParameterError(f"rates.n_mech: expected a divisor of n_velocity={self.n_velocity}, got {self.n_mech}")
        if self.method not in ("tustin", "zoh"):
            raise ParameterError(f"rates.method: expected 'tustin' or 'zoh', got {self.method!r}")

    @property
    def dt_current(self) -> float:
        """Current-loop (and electrical) sample time [s]."""
        return 1.0 / self.f_current

    @property
    def dt_mech(self) -> float:
        """Mechanical step [s]."""
        return self.n_mech / self.f_current

    @property
    def dt_velocity(self) -> float:
        """Velocity-loop sample time [s]."""
        return self.n_velocity / self.f_current

    @property
    def dt_position(self) -> float:
        """Position-loop sample time [s]."""
        return self.n_velocity * self.n_position / self.f_current

    def finer(self, factor: int) -> "LoopRates":
        """The same loop structure with every rate multiplied by ``factor``."""
        return dataclasses.replace(self, f_current=self.f_current * factor)


def command_limits(servo: ServoParams) -> tuple[np.ndarray, np.ndarray]:
    """The largest speed [rad/s] and torque [N m] target of each axis, ``V_max/Ke`` and ``Kt I_max``: where the
    velocity loop clamps its command (the back-EMF takes the whole voltage there) and the current loop its current;
    what the bridge clamps its targets to, what a drive takes, and what a path may ask of the motors."""
    return np.asarray(servo.V_max / servo.Ke, dtype=float), np.asarray(servo.Kt * servo.I_max, dtype=float)


def _fmt(x: float) -> str:
    return f"{x:.4g}"


def axis_cells(value: npt.ArrayLike) -> list[str]:
    """One cell per axis of ``value`` ``(..., n_axes)``: the value, or ``lo..hi`` over the leading (batch)
    dimensions."""
    arr = np.asarray(value, dtype=float)
    arr = arr.reshape(-1, arr.shape[-1] if arr.ndim else 1)
    lo, hi = arr.min(axis=0), arr.max(axis=0)
    return [
        _fmt(a) if a == b or not (np.isfinite(a) and np.isfinite(b)) else f"{_fmt(a)}..{_fmt(b)}"
        for a, b in zip(lo, hi)
    ]


def axis_table(
    title: str, rows: Sequence[tuple[str, str, list[str]]], n_axes: int = N_AXES, markdown: bool = False
) -> str:
    """``title`` and a table of ``rows`` ``[(name, unit, cells)]``, one column per axis.

    As text, a row whose cells are all equal shows its value once ("every axis"); as markdown (a notebook's
    rendering) every cell is shown.
    """
    head = [f"axis {k}" for k in range(n_axes)]
    if markdown:
        lines = [title, "", "| field | unit | " + " | ".join(head) + " |", "|---|---|" + "---:|" * n_axes]
        lines += [
            f"| {name} | {unit} | " + " | ".join(cells if len(cells) == n_axes else cells * n_axes) + " |"
            for name, unit, cells in rows
        ]
        return "\n".join(lines)
    wn = max([5] + [len(name) for name, _, _ in rows])
    wu = max([4] + [len(unit) for _, unit, _ in rows])
    wc = max([6] + [len(c) for _, _, cells in rows for c in cells])
    lines = [title, f"  {'field':<{wn}}  {'unit':<{wu}}  " + "  ".join(f"{h:>{wc}}" for h in head)]
    for name, unit, cells in rows:
        same = len(set(cells)) == 1
        shown = f"{cells[0]:>{wc}}  (every axis)" if same else "  ".join(f"{c:>{wc}}" for c in cells)
        lines.append(f"  {name:<{wn}}  {unit:<{wu}}  {shown}")
    return "\n".join(lines)


def describe(p: DataclassInstance, markdown: bool = False) -> str:
    """A per-axis parameter set as a table of its fields with their units (its ``repr``; ``markdown`` for notebooks).

    A batch of parameter sets shows ``lo..hi`` over the batch; traced values (inside ``jit``) only their shapes.
    """
    cls = type(p)
    values = arrays(p)
    choices = ", ".join(f"{f.name}={getattr(p, f.name)!r}" for f in static_fields(cls))
    shape = np.shape(next(iter(values.values()), ()))
    if not all(_is_concrete(v) for v in values.values()):
        return f"{cls.__name__}(traced, shape {shape}{', ' + choices if choices else ''})"
    n = shape[-1] if shape else 1
    batch = f", a batch of {int(np.prod(shape[:-1]))} sets (lo..hi over the batch)" if len(shape) > 1 else ""
    title = f"{cls.__name__}: {n} axes{batch}" + (f", {choices}" if choices else "")
    rows = []
    for f in array_fields(cls):
        try:
            cells = axis_cells(values[f.name])
        except (TypeError, ValueError):
            cells = [repr(values[f.name])[:40]]
        rows.append((f.name, f.metadata["unit"], cells))
    return axis_table(f"**{title}**" if markdown else title, rows, n, markdown)


def field_docs(cls: type[DataclassInstance]) -> list[tuple[str, Any, str, str]]:
    """(name, default, unit, doc) for every field of a parameter class."""
    return [(f.name, f.default, f.metadata["unit"], f.metadata["doc"]) for f in fields(cls)]


def _from_mapping(cls: type[_P], values: Mapping[str, Any], base: _P | None) -> _P:
    inputs.check_keys(values, cls.__name__, [f.name for f in fields(cls)], ParameterError, what="field")
    base = base if base is not None else cls.default()
    static = {f.name: f for f in static_fields(cls)}
    changes: dict[str, Any] = {}
    for name, v in values.items():
        where = f"{cls.__name__}.{name}"
        if name in static:
            changes[name] = inputs.choice(v, where, static[name].metadata["choices"], ParameterError)
        elif isinstance(v, list):
            if len(v) != N_AXES:
                raise ParameterError(
                    f"{where}: expected a number or a list of {N_AXES} numbers (one per axis), got a list of {len(v)}"
                )
            changes[name] = np.array(
                [inputs.number(x, f"{where}[{k}]", ParameterError, finite=False) for k, x in enumerate(v)]
            )
        else:
            changes[name] = np.full((N_AXES,), inputs.number(v, where, ParameterError, finite=False))
    out = dataclasses.replace(base, **changes)
    validate(out)
    return out


def _is_concrete(x: object) -> bool:
    return not isinstance(x, jax.core.Tracer)


def validate(p: DataclassInstance) -> None:
    """Check shapes, finiteness and signs of every field (host-side, concrete values only).

    Raises :class:`ParameterError` with the field name, what was expected and what was
    found.  Tracers (inside jit/vmap/grad) are skipped: validate before tracing.
    """
    cls = type(p)
    for f in static_fields(cls):
        v = getattr(p, f.name)
        if v not in f.metadata["choices"]:
            raise ParameterError(f"{cls.__name__}.{f.name}: expected one of {f.metadata['choices']}, got {v!r}")
    shape = None
    for f in array_fields(cls):
        v = getattr(p, f.name)
        if not _is_concrete(v):
            return
        arr = np.asarray(v)
        where = f"{cls.__name__}.{f.name}"
        if arr.ndim == 0 or arr.shape[-1] != N_AXES:
            raise ParameterError(f"{where}: expected shape (..., {N_AXES}) (one value per axis), got {arr.shape}")
        if shape is None:
            shape = arr.shape
        elif arr.shape != shape:
            raise ParameterError(f"{where}: expected shape {shape} like the other fields, got {arr.shape}")
        if not np.issubdtype(arr.dtype, np.number):
            raise ParameterError(f"{where}: expected numbers, got dtype {arr.dtype}")
        bad = ~np.isfinite(arr)
        if bad.any():
            raise ParameterError(
                f"{where}: expected finite values [{f.metadata['unit']}], got {arr[bad].flat[0]} at {_index(bad)}"
            )
        kind = f.metadata["kind"]
        bad = arr <= 0 if kind == "positive" else arr < 0 if kind == "nonnegative" else np.zeros_like(bad)
        if bad.any():
            word = "positive" if kind == "positive" else "non-negative"
            raise ParameterError(
                f"{where}: expected a {word} value [{f.metadata['unit']}], got {arr[bad].flat[0]} at {_index(bad)}"
            )
        _check_bounds(p, f, arr)


def bounds(f: dataclasses.Field[Any]) -> tuple[float, float | str, str] | None:
    """``(low, high, why)`` of a field: its physically meaningful range, ``high`` a number or the name of the rating
    field the value may not exceed; None for a field without bounds."""
    found: tuple[float, float | str, str] | None = f.metadata.get("bounds")
    return found


def _check_bounds(p: DataclassInstance, f: dataclasses.Field[Any], arr: npt.NDArray[Any]) -> None:
    b = bounds(f)
    if b is None:
        return
    low, high, why = b
    top = np.asarray(getattr(p, high), dtype=float) if isinstance(high, str) else high
    bad = (arr < low) | (arr > top)
    if bad.any():
        limit = f"{high} = {np.broadcast_to(top, arr.shape)[bad].flat[0]:.6g}" if isinstance(high, str) else f"{high:g}"
        raise ParameterError(
            f"{type(p).__name__}.{f.name}: expected {low:g} to {limit} [{f.metadata['unit']}] "
            f"({why}), got {arr[bad].flat[0]:.6g} at {_index(bad)}"
        )


def _index(mask: npt.NDArray[np.bool_]) -> str:
    idx = np.argwhere(mask)[0]
    return f"axis {idx[-1]}" if len(idx) == 1 else f"index {tuple(int(i) for i in idx)}"


def stack(params_list: Sequence[_T]) -> _T:
    """Stack parameter sets along a new leading batch axis (for vmapped runs)."""
    out: _T = jax.tree.map(lambda *xs: np.stack(xs), *params_list)
    return out
