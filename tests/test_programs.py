"""Traced programs kept on disk (pusupu_jax.programs): loaded instead of traced, bitwise the same, keyed on all they
depend on, and a bad file traced again.  Small functions here: the tuner's gradient goes through the same class in
tests/test_batch.py (a Problem built again with nothing in memory loads it and gives the same numbers), and every
tuning run of the suite (tests/test_cli.py's resumed run, Ray's workers) runs through it."""

import threading
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax import programs
from pusupu_jax.programs import SUFFIX, Program, UnstableKey, describe


class Pair(NamedTuple):
    a: jax.Array
    b: jax.Array


def _counted():
    traces = []

    def fun(x, p: Pair, table: dict):
        traces.append(1)  # runs only while tracing
        y = jnp.sin(x) * p.a + table["k"] @ p.b
        return {"y": y, "sum": (jnp.sum(y), jax.grad(lambda v: jnp.sum(jnp.cos(v) * p.a))(x))}

    return fun, traces


ARGS = (jnp.linspace(0.0, 1.0, 3), Pair(jnp.arange(3.0), jnp.ones(2)), {"k": jnp.eye(3, 2)})
LONGER = (jnp.zeros(4), Pair(jnp.arange(4.0), jnp.ones(2)), {"k": jnp.ones((4, 2))})


def _same(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    assert all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_a_second_program_loads_the_first_ones_file_instead_of_tracing(tmp_path):
    fun, traces = _counted()
    first = Program(fun, "key", folder=tmp_path)
    out = first(*ARGS)
    assert len(traces) == 1 and first.loaded == 0
    assert len(list(tmp_path.glob("*" + SUFFIX))) == 1
    _same(out, jax.jit(fun)(*ARGS))  # the exported program's results are the function's, bitwise
    traces.clear()
    second = Program(fun, "key", folder=tmp_path)
    _same(second(*ARGS), out)
    assert traces == [] and second.loaded == 1
    fed_back = second(ARGS[0] + out["sum"][1], *ARGS[1:])  # outputs placed as plain jit's: no second compile
    assert second.loaded == 1 and next(iter(second._calls.values()))._cache_size() == 1  # one load per signature
    _same(fed_back, jax.jit(fun)(ARGS[0] + out["sum"][1], *ARGS[1:]))


@pytest.mark.filterwarnings("ignore:pusupu_jax.programs. not exported")  # the refused one
def test_a_program_compiled_ahead_is_what_its_first_call_runs(tmp_path):
    """``compile_ahead`` with arguments of the call's types (zeros) traces and compiles in a thread of its own; the
    first call then waits for it, and neither traces nor compiles in its thread (JAX's own events), and gives the direct
    jit's results.  Arguments of other types are compiled at their call.  A compile that fails ahead is left to the
    first call, which raises the function's own error."""
    from jax import monitoring

    fun, traces = _counted()
    program = Program(fun, "key", folder=tmp_path)
    program.compile_ahead(*jax.tree.map(jnp.zeros_like, ARGS))
    program.compile_ahead(*jax.tree.map(jnp.zeros_like, ARGS))  # once per signature
    compiles = []

    def on_event(event, duration, **kw):
        # this thread's: the thread of compile_ahead may still be at it
        if event.endswith(("backend_compile_duration", "jaxpr_trace_duration")) and threading.main_thread() is (
            threading.current_thread()
        ):
            compiles.append((event, kw.get("fun_name")))

    monitoring.register_event_duration_secs_listener(on_event)
    try:
        out = program(*ARGS)
        # the program's own (its traced function, its exported call), not the host copies' small programs
        assert not {name for _, name in compiles} & {"flat", "call", "jit(call)"} and len(traces) == 1, compiles
        _same(out, jax.jit(fun)(*ARGS))
        traces.clear()
        program(*LONGER)  # another signature: traced at its call
        assert len(traces) == 1 and "flat" in {name for _, name in compiles}
    finally:
        monitoring.unregister_event_duration_listener(on_event)

    def refuses(x):
        if x.shape[0] == 3:
            raise ValueError("no three here")
        return x

    failing = Program(refuses, "refuses", folder=tmp_path)
    failing.compile_ahead(jnp.zeros(3))
    with pytest.raises(ValueError, match="no three here"):
        failing(jnp.ones(3))


def test_another_key_or_signature_is_another_program(tmp_path):
    fun, traces = _counted()
    Program(fun, "key", folder=tmp_path)(*ARGS)
    Program(fun, "other key", folder=tmp_path)(*ARGS)
    p = Program(fun, "key", folder=tmp_path)
    p(*LONGER)
    p(*(x.astype(jnp.float32) for x in jax.tree.leaves(ARGS[:1])), *ARGS[1:])
    assert len(traces) == 4 and p.loaded == 0
    assert len(list(tmp_path.glob("*" + SUFFIX))) == 4
    named_late = Program(fun, lambda: "other key", folder=tmp_path)  # a key taken when the program is first needed
    named_late(*ARGS)
    assert named_late.loaded == 1 and len(traces) == 4


@pytest.mark.parametrize("damage", ["truncated", "one byte flipped", "made for other arguments"])
def test_a_damaged_or_misplaced_file_is_traced_again_and_replaced(tmp_path, damage):
    fun, traces = _counted()
    want = Program(fun, "key", folder=tmp_path)(*ARGS)
    (path,) = tmp_path.glob("*" + SUFFIX)
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[:100])
    elif damage == "one byte flipped":  # in the module's bytes: the checksum, not the parser, has to catch it
        path.write_bytes(data[: len(data) // 2] + bytes([data[len(data) // 2] ^ 1]) + data[len(data) // 2 + 1 :])
    else:  # this file under the name of the program for a longer x
        leaves, tree = jax.tree.flatten(LONGER)
        path = tmp_path / (Program(fun, "key").digest(tree, [str(jax.typeof(x)) for x in leaves]) + SUFFIX)
        path.write_bytes(data)
        want = jax.jit(_counted()[0])(*LONGER)  # a function of its own: its trace is not counted
    reason = "other argument types" if damage == "made for other arguments" else "checksum|did not load"
    p = Program(fun, "key", folder=tmp_path)
    with pytest.warns(UserWarning, match=reason):
        got = p(*(LONGER if damage == "made for other arguments" else ARGS))
    _same(got, want)
    assert len(traces) == 2 and p.loaded == 0
    again = Program(fun, "key", folder=tmp_path)
    again(*(LONGER if damage == "made for other arguments" else ARGS))
    assert again.loaded == 1 and len(traces) == 2


def test_other_library_versions_name_another_file(tmp_path, monkeypatch):
    fun, traces = _counted()
    Program(fun, "key", folder=tmp_path)(*ARGS)
    monkeypatch.setattr(programs, "_versions", lambda: "jax=0.0.0")
    p = Program(fun, "key", folder=tmp_path)
    p(*ARGS)
    assert p.loaded == 0 and len(traces) == 2 and len(list(tmp_path.glob("*" + SUFFIX))) == 2


def test_a_function_jax_export_refuses_is_only_jitted(tmp_path):
    def noisy(x):
        jax.debug.callback(lambda v: None, x)  # a host callback: jax.export refuses it
        return 2.0 * x

    with pytest.warns(UserWarning, match="not exported"):
        out = Program(noisy, "key", folder=tmp_path)(ARGS[0])
    _same(out, 2.0 * ARGS[0])
    assert not list(tmp_path.iterdir())


def test_what_has_no_stable_description_is_only_jitted(tmp_path):
    fun, traces = _counted()
    args = (jax.tree_util.Partial(lambda v: v, ARGS[0]), *ARGS[1:])  # a function in the arguments' structure

    def unwrap(x, p, table):
        return fun(x(), p, table)

    with pytest.warns(UserWarning, match="not kept on disk"):
        out = Program(unwrap, "key", folder=tmp_path)(*args)
    _same(out, jax.jit(fun)(*ARGS))
    assert not list(tmp_path.iterdir())


def test_descriptions_are_equal_for_equal_values_only():
    a = {"x": np.arange(3.0), "p": Pair(1, "s"), "t": (None, 2.5)}
    assert describe(a) == describe({"t": (None, 2.5), "p": Pair(1, "s"), "x": np.arange(3.0)})
    assert describe(a) != describe(a | {"x": np.nextafter(np.arange(3.0), 9)})  # last bit of one element
    assert describe(Pair(1, 2)) != describe((1, 2))
    assert describe(jax.tree.structure(Pair(1, 2))) != describe(jax.tree.structure((1, 2)))
    with pytest.raises(UnstableKey, match="builtins.object"):
        describe(object())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        describe(jnp.ones(2))  # a jax array by its values


KEPT_IN_A_PROCESS = """
import json, sys
from pathlib import Path

import jax, jax.numpy as jnp, mujoco
from mujoco import mjx

jax.config.update("jax_enable_x64", True)
from pusupu_jax.loops import PIState
from pusupu_jax.programs import Program

model = mjx.put_model(mujoco.MjModel.from_xml_string(
    "<mujoco><worldbody><body><joint type='slide'/><geom size='.1' mass='2'/></body></worldbody></mujoco>"))


def run(q):  # a run's carry: the cascade's states and MJX's data, node types jax.export does not know
    data = mjx.forward(model, mjx.make_data(model).replace(qpos=q))
    return PIState(q, 2.0 * q, jnp.sum(data.qfrc_bias)), data


program = Program(run, "key", folder=Path(sys.argv[1]), to_host=False)
state, data = program(jnp.ones(1))
print(json.dumps({"loaded": program.loaded, "values": [repr(float(jnp.sum(x))) for x in jax.tree.leaves((state, data))],
                  "types": [type(state).__name__, type(data).__name__]}))
"""


def test_outputs_holding_the_cascades_states_and_mjx_data_are_kept_and_read_in_a_new_process(tmp_path):
    """A run's carry (the cascade's NamedTuples, MJX's data with its static arrays) as a program's outputs: the file
    names those node types, and a new process, which has registered none of them, reads it back with its outputs'
    structure and the same values to the bit, without tracing."""
    import json
    import subprocess
    import sys

    script = tmp_path / "kept.py"
    script.write_text(KEPT_IN_A_PROCESS)
    runs = [
        subprocess.run([sys.executable, script, tmp_path / "programs"], capture_output=True, text=True) for _ in "ab"
    ]
    assert all(r.returncode == 0 and "Warning" not in r.stderr for r in runs), [r.stderr for r in runs]
    first, second = (json.loads(r.stdout.splitlines()[-1]) for r in runs)  # MJX prints its GPU backends' absence
    assert (first["loaded"], second["loaded"]) == (0, 1)
    assert second["values"] == first["values"] and second["types"] == first["types"] == ["PIState", "Data"]
    (path,) = (tmp_path / "programs").glob("*" + SUFFIX)
    assert b"pusupu_jax.loops:PIState" in path.read_bytes()[:400]


def test_a_file_naming_a_type_from_elsewhere_is_traced_again(tmp_path):
    """A file whose list of node types names a module outside pusupu_jax and MJX (checksum made good): nothing is
    imported from it; the program is traced again and the file replaced."""
    import hashlib

    from pusupu_jax.loops import PIState

    def fun(x):
        return PIState(x, 2.0 * x, jnp.sum(x))

    want = Program(fun, "key", folder=tmp_path)(ARGS[0])
    (path,) = tmp_path.glob("*" + SUFFIX)
    body = path.read_bytes()[32:]
    assert b"pusupu_jax.loops:PIState" in body
    body = body.replace(b"pusupu_jax.loops:PIState", b"os:system".ljust(len(b"pusupu_jax.loops:PIState")))
    path.write_bytes(hashlib.sha256(body).digest() + body)
    p = Program(fun, "key", folder=tmp_path)
    with pytest.warns(UserWarning, match="did not load.*outside"):
        _same(p(ARGS[0]), want)
    assert p.loaded == 0 and Program(fun, "key", folder=tmp_path)(ARGS[0]) is not None


def test_the_outputs_structure_comes_from_the_file_without_a_trace(tmp_path):
    fun, traces = _counted()
    Program(fun, "key", folder=tmp_path)(*ARGS)
    traces.clear()
    loaded = Program(fun, "key", folder=tmp_path)
    shape = loaded.eval_shape(*ARGS)
    assert traces == [] and loaded.loaded == 1
    want = jax.eval_shape(fun, *ARGS)
    assert jax.tree.structure(shape) == jax.tree.structure(want)
    assert [(x.shape, x.dtype) for x in jax.tree.leaves(shape)] == [(x.shape, x.dtype) for x in jax.tree.leaves(want)]


def test_static_data_reads_back_as_it_was_described():
    """A node's static data written to a kept file and read back describes as before, NumPy scalars included
    (np.float64 is a Python float too): the structure of a loaded program's outputs names the programs it enters."""
    import json

    static = (np.int64(18), np.float64(0.5), np.bool_(True), 3, 2.5, "s", None, [np.int32(1)], ())
    back = programs._decode(json.loads(json.dumps(programs._encode(static))))
    assert describe(back) == describe(static)
