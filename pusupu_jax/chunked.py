"""Long runs on the host: a batch of rollouts cut into calls of one compiled chunk program, so that any path length
runs the same programs (the start and one chunk), with the carry kept at chosen periods (the training windows' start
states).  The start is the plant's rest, one program for every mode, then the controllers' states from it.

The start's programs and the chunk are kept on disk beside the compilation cache (:mod:`pusupu_jax.programs`), so
that a later process loads them instead of tracing them again: some 6 s of CPU for the default machine's start and
chunk, paid by every ``pusupu sim``, experiment and tuning run before its first period (a batch laid over several
devices traces them in its process)."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, Callable, Sequence, cast

import jax
import jax.numpy as jnp
import numpy as np

from . import cascade as cascade_
from . import compliance as compliance_law
from . import hybrid as hybrid_law
from .params import LoopRates, ServoParams
from .plant import AxisPlant
from .programs import Program, describe
from .sim import Carry, Rest, initial_carry, period_dt, plant_rest, plant_side, rollout_chunk
from .trace import Trace

if TYPE_CHECKING:
    from .plant import Plant
    from .plant.geometry import Geometry


CHUNK = 250  # periods per call of run_chunked's compiled program
REST_BLOCK = 64  # a batch of at least this many runs computes its rests this many at a time (_MemberRests)


def _per_member(tree: Any, axis: int | None, n: int) -> Any:
    """``tree``'s leaves as NumPy arrays with a leading axis of ``n`` members: as they are where batched (``axis``
    0), repeated where shared (None: nothing).  So every caller of :func:`run_chunked` runs the same programs: shared
    or batched gains, arrays or Python numbers (whose weak types would name programs of their own)."""
    if tree is None:
        return None
    if axis == 0:
        return jax.tree.map(np.asarray, tree)
    return jax.tree.map(lambda x: np.broadcast_to(np.asarray(x), (n,) + np.shape(x)), tree)


def _programs_mode(params: ServoParams, outer: str) -> tuple[ServoParams, str]:
    """The gains and mode whose programs run ``outer``: the PID baseline is the PID with velocity feedforward at
    ``Kff = 0`` (:func:`pusupu_jax.cascade.position_tick`), so it runs that mode's programs with ``Kff_pid`` zero (the
    same numbers, one compile for both baselines)."""
    if cascade_.control_mode(outer).law != cascade_.Law.PID:
        return params, outer
    return params.replace(Kff_pid=np.zeros_like(np.asarray(params.Kff_pid))), cascade_.Mode.PID_FF


def _init(
    plant: Plant,
    rates: LoopRates,
    outer: str,
    start: str,
) -> Callable[..., Carry]:
    """:func:`~pusupu_jax.sim.initial_carry` vmapped over a batch (every argument per member but the shared
    ``compliance``: :func:`run_chunked` lays them out so), from the plant's rest computed before (:func:`_rest`), its
    last argument."""

    def init(
        params: ServoParams,
        model: Any,
        first: Any,
        hybrid: hybrid_law.HybridGains | None,
        compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None,
        rest: Rest,
    ) -> Carry:
        return initial_carry(
            params,
            model,
            first,
            plant=plant,
            rates=rates,
            outer=outer,
            hybrid=hybrid,
            start=start,
            compliance=compliance,
            rest=rest,
        )

    return jax.vmap(init, in_axes=(0, 0, 0, 0, None, 0))


def _rest_one(plant: Plant, dt_mech: float) -> Callable[..., Rest]:
    """:func:`~pusupu_jax.sim.plant_rest` of one run: ``(params, model) -> Rest``."""

    def rest(params: ServoParams, model: Any) -> Rest:
        return plant_rest(plant, plant.prepare(*plant_side(params, model), dt_mech))

    return rest


def _rest(plant: Plant, dt_mech: float) -> Callable[..., Rest]:
    """:func:`_rest_one` vmapped over a batch (laid over several devices: :func:`_laid_over`)."""
    return jax.vmap(_rest_one(plant, dt_mech))


def _chunk(plant: Plant, rates: LoopRates, outer: str) -> Callable[..., tuple[dict[str, Any], Carry]]:
    """:func:`~pusupu_jax.sim.rollout_chunk` vmapped over a batch (laid out as :func:`_init`'s)."""

    def chunk(
        params: ServoParams,
        model: Any,
        reference: Any,
        hybrid: hybrid_law.HybridGains | None,
        compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None,
        carry: Carry,
        n_valid: jax.Array,
    ) -> tuple[dict[str, Any], Carry]:
        return rollout_chunk(
            params,
            model,
            reference,
            carry,
            n_valid,
            plant=plant,
            rates=rates,
            outer=outer,
            hybrid=hybrid,
            compliance=compliance,
        )

    return jax.vmap(chunk, in_axes=(0, 0, 0, 0, None, 0, None))


@functools.lru_cache(maxsize=None)
def _rest_program(plant: Plant, dt_mech: float, block: bool = False) -> Program:
    """The plant's rest of one run, ``(params, model) -> Rest`` (cached per static arguments), or with ``block`` of a
    batch (:func:`_rest`), kept on disk (:class:`~pusupu_jax.programs.Program`): a later process loads it rather than
    tracing it again.  One program for every mode, start, rates of the same mechanical step and batch size
    (:class:`_MemberRests`)."""
    return Program(
        _rest(plant, dt_mech) if block else _rest_one(plant, dt_mech),
        lambda: describe(("rests" if block else "rest", plant.key(), dt_mech)),
        to_host=False,
    )


class _MemberRests:
    """A batch's rests from a program of a fixed size, whatever the batch's: the rest is a few MJX calls per run,
    once, where a program per batch size cost a compile each (some 8 s of CPU for the default machine).  Below
    ``block`` runs, a call per run of the one-run program, stacked; from ``block`` runs on, a call per ``block`` runs
    of that program vmapped (the last block filled with copies of the batch's last run, dropped after), so that
    thousands of runs take tens of calls: 4096 runs a call each took more than 4.5 minutes on an H200's host, in
    the calls and in stacking their 4096 results."""

    def __init__(self, plant: Plant, dt_mech: float, block: int = REST_BLOCK) -> None:
        self.program = _rest_program(plant, dt_mech)
        self.blocks = _rest_program(plant, dt_mech, block=True)
        self.block = block

    @staticmethod
    def _members(params: ServoParams, models: Any) -> list[tuple[ServoParams, Any]]:
        n = jax.tree.leaves(models)[0].shape[0]
        return [jax.tree.map(lambda x: x[b], (params, models)) for b in range(n)]

    def __call__(self, params: ServoParams, models: Any) -> Rest:
        n = jax.tree.leaves(models)[0].shape[0]
        if n < self.block:
            rests = [self.program(*member) for member in self._members(params, models)]
            return cast(Rest, jax.tree.map(lambda *r: jnp.stack(r), *rests))
        blocks = [np.minimum(np.arange(b, b + self.block), n - 1) for b in range(0, n, self.block)]
        rests = [self.blocks(*jax.tree.map(lambda x: x[rows], (params, models))) for rows in blocks]
        return cast(Rest, jax.tree.map(lambda *r: jnp.concatenate(r)[:n], *rests))

    def eval_shape(self, params: ServoParams, models: Any) -> Any:
        n = jax.tree.leaves(models)[0].shape[0]
        one = self.program.eval_shape(*jax.tree.map(lambda x: x[0], (params, models)))
        return jax.tree.map(lambda x: jax.ShapeDtypeStruct((n,) + x.shape, x.dtype), one)  # type: ignore[no-untyped-call]  # jax leaves it unannotated


class _Rested:
    """A batch's start in two programs: the plant's rest, then the controllers' states from it.  Both kept on disk
    (:func:`_start_program`), or, for a batch laid over several devices, jitted in this process (:func:`_laid_over`:
    no :meth:`eval_shape` then)."""

    def __init__(self, rest: Any, finish: Any) -> None:
        self.rest, self.finish = rest, finish

    def __call__(self, params: ServoParams, models: Any, first: Any, hybrid: Any, compliance: Any) -> Carry:
        return cast(Carry, self.finish(params, models, first, hybrid, compliance, self.rest(params, models)))

    def eval_shape(self, params: ServoParams, models: Any, first: Any, hybrid: Any, compliance: Any) -> Any:
        """The carries' structure, nothing traced where both programs are on disk."""
        rest = self.rest.eval_shape(params, models)
        return self.finish.eval_shape(params, models, first, hybrid, compliance, rest)


@functools.lru_cache(maxsize=None)
def _start_program(plant: Plant, rates: LoopRates, outer: str, start: str) -> _Rested:
    """The start of :func:`run_chunked` (cached per static arguments).  Its plant's part (the state at rest and the
    static equilibrium that the holding torques are solved from) is the same in every mode, so that the modes, the
    IMC's two forms, a compliant run and its plain one, and both starts share its program, whose compile is most of a
    start's.  The controllers' states follow in a program per mode with no plant step in it.  The default machine's
    start of one run, on the 2-core CPU at XLA's default optimisation: the rest 6.5 s of CPU to trace, compile and
    run; the controllers' 1.2 to 2.0 s to trace and compile."""
    static = (rates, cascade_.control_mode(outer), start)
    finish = Program(
        _init(plant, rates, outer, start),
        lambda: describe(("start", plant.key(), static)),
        to_host=False,
    )
    return _Rested(_MemberRests(plant, rates.dt_mech), finish)


@functools.lru_cache(maxsize=None)
def _chunk_program(plant: Plant, rates: LoopRates, outer: str) -> Program:
    """The chunk's program (cached per static arguments: one compile serves every path length, and runs that keep
    carries at marks or none), kept on disk as :func:`_rest_program`'s."""
    static = (rates, cascade_.control_mode(outer))
    fun = _chunk(plant, rates, outer)
    return Program(fun, lambda: describe(("chunk", plant.key(), static)), to_host=False)


@functools.lru_cache(maxsize=None)
def _laid_over(fun: Callable[..., Any], *static: Any) -> jax.stages.Wrapped:
    """``fun(*static)`` jitted in this process only: for arguments laid over several devices, which a program kept
    on disk (exported for one device) does not take."""
    return jax.jit(fun(*static))


def carry_structure(
    params: ServoParams,
    models: Any,
    first: Any,
    *,
    plant: Plant = AxisPlant(),
    rates: LoopRates = LoopRates(),
    outer: str = "imc",
    hybrid: hybrid_law.HybridGains | None = None,
    start: str = "rest",
) -> Any:
    """The structure of :func:`run_chunked`'s carries (a tree of ``jax.ShapeDtypeStruct``, batch axis first) for
    ``models`` and the references' first samples ``first``, from its start program without running it (read from
    disk where it is kept there)."""
    params, outer = _programs_mode(params, outer)
    n = jax.tree.leaves(models)[0].shape[0]
    params, hybrid = _per_member(params, None, n), _per_member(hybrid, None, n)
    return _start_program(plant, rates, outer, start).eval_shape(params, models, first, hybrid, None)


def run_chunked(
    params: ServoParams,
    models: Any,
    reference: Any,
    *,
    plant: Plant = AxisPlant(),
    rates: LoopRates = LoopRates(),
    outer: str = "imc",
    hybrid: hybrid_law.HybridGains | None = None,
    start: str = "rest",
    compliance: tuple[compliance_law.AdmittanceGains, Geometry] | None = None,
    params_axis: int | None = None,
    hybrid_axis: int | None = None,
    marks: Sequence[int] = (),
    chunk: int = CHUNK,
    to_end: bool = True,
) -> tuple[Trace, Carry | None]:
    """A batch of runs, each :func:`~pusupu_jax.sim.rollout` of its ``models[b]`` over ``reference[b]``
    ``(B, N, ...)``, cut into calls of one compiled program of ``chunk`` periods (host-side): ``(trace (B, N, ...),
    carries (B, len(marks), ...))``.

    ``params`` (and ``hybrid``) are shared, or batched along their leading axis when ``params_axis``
    (``hybrid_axis``) is 0; ``compliance``: ``(AdmittanceGains, Geometry)``, shared, or None; ``models`` is batched
    (the plant's per-run arrays, e.g. :meth:`MJXPlant.variant`'s).  Every path length runs the same two compiled
    programs (the start and one chunk), so a horizon that changes compiles nothing; and shared gains run as batched
    ones (repeated per member), so that a simulation, a tune and a grid of gains share them too.  The last chunk runs
    past the path's end, on its last sample held; what it records there is dropped.

    ``marks``: periods at which to keep the carry (the start states of windows, for ``rollout(init=...)``): the
    chunks stop at them (:func:`~pusupu_jax.sim.rollout_chunk`'s ``n_valid``, the same program), and run whole between
    them.  Different programs round differently: a run agrees with :func:`~pusupu_jax.sim.rollout`'s to float64
    rounding, not bit for bit (``tests/test_windows.py``).  ``to_end=False`` stops at the last mark (one period in, at
    least), for the carries alone (a tuner's start states): the trace then covers the periods run, and the carries
    are those of the whole run, bit for bit (the same calls up to there).
    """
    init: Callable[..., Carry]
    step: Callable[..., tuple[dict[str, Any], Carry]]
    params, outer = _programs_mode(params, outer)
    n = jax.tree.leaves(models)[0].shape[0]
    params, hybrid = _per_member(params, params_axis, n), _per_member(hybrid, hybrid_axis, n)
    compliance = None if compliance is None else jax.tree.map(np.asarray, compliance)
    if any(len(x.sharding.device_set) > 1 for x in jax.tree.leaves(models) if isinstance(x, jax.Array)):
        init = _Rested(
            _laid_over(_rest, plant, rates.dt_mech),
            _laid_over(_init, plant, rates, outer, start),
        )
        step = _laid_over(_chunk, plant, rates, outer)
    else:
        init = _start_program(plant, rates, outer, start)
        step = _chunk_program(plant, rates, outer)
    host = jax.tree.map(np.asarray, reference)
    n = jax.tree.leaves(host)[0].shape[1]
    if any(not 0 <= m < n for m in marks) or not (to_end or marks):
        raise ValueError(f"run_chunked: expected marks in [0, {n}) (some, unless to_end), got {list(marks)}")
    carry = init(params, models, jax.tree.map(lambda x: x[:, 0], host), hybrid, compliance)
    kept: dict[int, Carry]
    records: list[tuple[dict[str, Any], int]]
    kept, records, done = {}, [], 0
    for stop in sorted(set(marks) | {n if to_end else max(1, *marks)}):  # a trace of one period at least
        while done < stop:
            k = min(chunk, stop - done)
            pad = [(0, 0), (0, chunk - k)]  # the last sample held
            piece = jax.tree.map(
                lambda x: np.pad(x[:, done : done + k], pad + [(0, 0)] * (x.ndim - 2), mode="edge"), host
            )
            rec, carry = step(params, models, piece, hybrid, compliance, carry, np.int32(k))
            records.append((rec, k))
            done += k
        if done in marks:
            kept[done] = carry
    rec = jax.tree.map(
        lambda *x: np.concatenate([np.asarray(r)[:, :k] for r, (_, k) in zip(x, records)], axis=1),
        *[r for r, _ in records],
    )  # fetched at the end: the calls before queue without waiting
    # on the host: taken as arguments by other programs, as a plain jit's (uncommitted) outputs would be
    carries = jax.tree.map(lambda *c: np.stack(c, axis=1), *[kept[m] for m in marks]) if marks else None
    t = np.arange(done) * period_dt(rates, cascade_.control_mode(outer))
    return Trace(t=np.repeat(t[None], len(rec["theta"]), axis=0), **rec), carries
