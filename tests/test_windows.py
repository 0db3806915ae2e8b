"""Windows of a long run (what the tuner trains on) and controllers whose states survive a change of gains."""

import jax
import numpy as np
import pytest

from pusupu_jax import AxisLoad, ServoParams, rollout
from pusupu_jax.params import LoopRates, stack
from pusupu_jax.plant import AxisPlant
from pusupu_jax.chunked import run_chunked
from pusupu_jax.trajectories import axis_reference

SERVO = ServoParams.table1()
LOAD = AxisLoad.default().replace(inclination=np.full(6, 1.0))  # gravity along the rails: the integrators hold it
R = float(SERVO.lead[0]) / (2 * np.pi)
REF = axis_reference("sine", duration=1.2) / R  # motor angle [rad], 1200 position periods


def _chunked(mode="imc", marks=(), chunk=128, to_end=True):
    """The whole run cut into calls of ``chunk`` periods (a batch of one), and its carries at ``marks``."""
    trace, carries = run_chunked(
        SERVO, stack([LOAD]), np.asarray(REF)[None], outer=mode, marks=marks, chunk=chunk, to_end=to_end
    )
    return jax.tree.map(lambda x: x[0], trace), jax.tree.map(lambda x: x[0], carries)


def test_a_run_cut_into_chunks_is_the_whole_run_and_restarts_from_its_carries():
    """run_chunked (one program of 128 periods, called 10 times, stopping at the marks) runs what one scan over the
    1200 periods runs, and a window restarted from a kept carry runs that stretch of it.  Different compiled programs
    round differently, so the tolerance is float64 rounding: relative 1e-13 (observed 2e-16 on angles, 5e-15 on
    currents)."""
    for mode in ("imc", "pid"):
        whole = jax.jit(lambda r: rollout(SERVO, LOAD, r, outer=mode))(REF)
        trace, carries = _chunked(mode, marks=(0, 300, 901))
        for run in (trace, _chunked(mode)[0]):  # stopping at the marks, and whole chunks (one program)
            np.testing.assert_array_equal(run.t, np.asarray(whole.t))
            for field in ("theta", "omega", "current", "command"):
                a, b = np.asarray(getattr(whole, field)), getattr(run, field)
                np.testing.assert_allclose(b, a, rtol=0, atol=1e-13 * np.abs(a).max(), err_msg=f"{mode} {field}")
        # stopped at the last mark (a tuner's start states): the same carries, bit for bit, and the run up to there
        short, kept = _chunked(mode, marks=(0, 300, 901), to_end=False)
        assert len(short.t) == 901
        np.testing.assert_array_equal(short.theta, trace.theta[:901])
        for a, b in zip(jax.tree.leaves(kept), jax.tree.leaves(carries)):
            np.testing.assert_array_equal(a, b)
        for j, k in enumerate((0, 300, 901)):
            window = rollout(SERVO, LOAD, REF[k : k + 200], outer=mode, init=jax.tree.map(lambda x: x[j], carries))
            for field in ("theta", "current"):
                a = np.asarray(getattr(whole, field))
                np.testing.assert_allclose(
                    np.asarray(getattr(window, field)),
                    a[k : k + 200],
                    rtol=0,
                    atol=1e-13 * np.abs(a).max(),
                    err_msg=f"{mode} {field} from {k}",
                )


@pytest.mark.parametrize("field", ["lambda1", "lambda2", "T0", "Kv", "Tv", "Kp_pid"])
def test_a_change_of_gains_mid_run_moves_the_command_in_proportion(field):
    """Restarted from the carry at 0.6 s with one gain 5 % higher, the first velocity command moves by at most 5 % of
    the command's range over the run: every state holds a physical value (a filtered signal, an integral term in
    output units), so the output changes only through the gains themselves, in proportion to their change.
    Observed: 4.0 % (lambda1), 3.9 % (lambda2), 2.4 % (Kp_pid), less for T0, Kv, Tv.  (A controllable canonical
    form's states scale with the gains; with it, a 1 % change of lambda1 moved the tuner's windowed objective from
    1.10 to 1.91, and 10 % to 59: docs/tuning.md.)
    """
    mode = "pid" if field == "Kp_pid" else "imc"
    _, carries = _chunked(mode, marks=(600,))
    whole = rollout(SERVO, LOAD, REF, outer=mode)
    changed = SERVO.replace(**{field: np.asarray(getattr(SERVO, field)) * 1.05})
    window = rollout(changed, LOAD, REF[600:610], outer=mode, init=jax.tree.map(lambda x: x[0], carries))
    command = np.asarray(whole.command)[:, 0]
    jump = abs(float(np.asarray(window.command)[0, 0]) - command[600])
    assert jump <= 0.05 * np.ptp(command), (field, jump, np.ptp(command))


@pytest.mark.skipif(len(jax.devices()) < 2, reason="one CPU: one host device")
def test_a_batch_laid_over_devices_runs_as_on_one():
    """Two runs laid over two devices (as the tuner's forward pass lays paths of different lengths: the start and
    the chunk jitted in this process) record what they record on one device (the kept programs), to float64
    rounding: relative 1e-13 (the two sides are different compiled programs)."""
    from jax.sharding import NamedSharding, PartitionSpec

    from pusupu_jax import chunked, devices

    loads = stack([LOAD, LOAD.replace(mass=LOAD.mass * 1.5)])
    refs = np.stack([np.asarray(REF)[:300]] * 2)
    mesh = devices.row_mesh(2)
    spread = jax.device_put(loads, NamedSharding(mesh, PartitionSpec("rows")))
    one, _ = run_chunked(SERVO, loads, refs, outer="pid")
    calls = chunked._laid_over.cache_info()
    laid, _ = run_chunked(SERVO, spread, refs, outer="pid")
    after = chunked._laid_over.cache_info()
    assert after.hits + after.misses == calls.hits + calls.misses + 3  # the rest, the controllers, the chunk
    for field in ("theta", "current", "command"):
        a, b = np.asarray(getattr(one, field)), np.asarray(getattr(laid, field))
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-13 * np.abs(a).max(), err_msg=field)
    assert np.abs(np.asarray(one.current[0]) - np.asarray(one.current[1])).max() > 1e-3  # the two loads differ


def test_a_large_batch_computes_its_rests_in_blocks_as_it_does_a_run_at_a_time():
    """From ``block`` runs on, a batch's rests come from the one-run program vmapped over blocks of ``block`` runs (the
    last filled with copies of the last run, dropped after): the same rests as a call per run, to float64 rounding
    (relative 1e-13: different compiled programs), in the batch's order."""
    from pusupu_jax.chunked import _MemberRests, _per_member

    n = 6
    loads = stack([LOAD.replace(mass=LOAD.mass * (1 + 0.2 * b)) for b in range(n)])
    params = _per_member(SERVO, None, n)
    each = _MemberRests(AxisPlant(), LoopRates().dt_mech, block=n + 1)(params, loads)
    blocks = _MemberRests(AxisPlant(), LoopRates().dt_mech, block=4)(params, loads)  # 4 runs, then 2 and 2 copies
    for a, b in zip(jax.tree.leaves(each), jax.tree.leaves(blocks)):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.shape[0] == n
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-13 * max(np.abs(a).max(), 1e-300))
    held = [np.asarray(x) for x in jax.tree.leaves(each) if np.ptp(np.asarray(x), axis=0).max() > 0]
    assert held, "the runs' rests differ with their loads"


def test_paths_of_any_length_run_one_compiled_chunk():
    """Two path lengths, with and without marks: one compile of the chunk (whole chunks and chunks that stop at marks
    are the same program) and of the start's controllers, which the PID baseline's runs take too: what lets every
    horizon of the experiments, the CLI and the tuner's forward passes share one program per mode and batch size.
    The plant's rest is one program for every mode: compiled here at most once (not at all when a test before ran
    another mode in this process)."""
    from pusupu_jax.chunked import _chunk_program, _start_program

    start = _start_program(AxisPlant(), LoopRates(), "pid_ff", "rest")
    program = _chunk_program(AxisPlant(), LoopRates(), "pid_ff")
    rest_before = start.rest.program.cache_size()
    sizes = []  # the executables after each run: whatever the first run compiled, the others compile nothing
    for n in (130, 700):
        for marks in ((), (0, 101, n - 1)):
            trace, carries = run_chunked(SERVO, stack([LOAD]), np.asarray(REF)[None, :n], outer="pid_ff", marks=marks)
            assert trace.theta.shape == (1, n, 6) and np.isfinite(trace.theta).all()
            assert carries is None if not marks else jax.tree.leaves(carries)[0].shape[:2] == (1, len(marks))
            sizes.append((program.cache_size(), start.finish.cache_size()))
    # the PID baseline is the PID + feedforward at Kff = 0: its run takes these programs, and compiles none of its own
    pid, _ = run_chunked(SERVO, stack([LOAD]), np.asarray(REF)[None, :130], outer="pid")
    assert np.isfinite(pid.theta).all()
    sizes.append((program.cache_size(), start.finish.cache_size()))
    assert sizes == sizes[:1] * 5 and sizes[0] >= (1, 1), sizes  # these are the programs that ran, and none added
    assert _chunk_program(AxisPlant(), LoopRates(), "pid").cache_size() == 0
    assert start.rest.program.cache_size() - rest_before <= 1 and start.rest.program.cache_size() >= 1
