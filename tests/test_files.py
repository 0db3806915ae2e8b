"""What the commands read and write: only regular files, opened without blocking, bounded in size and in the work they
imply; one line for every bad input.  Run as root, the commands once replaced device nodes, followed planted symlinks,
hung on FIFOs and ran out of memory on crafted checkpoints; each test here makes such paths under ``tmp_path``."""

import io
import json
import os
import socket
import stat
import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from pusupu_jax import inputs
from pusupu_jax.files import write_atomic
from pusupu_jax.params import ParameterError

ROOT = os.geteuid() == 0


def limited(code: str, timeout: float = 120, memory: int = 3 << 30) -> subprocess.CompletedProcess:
    """``python -c code`` with at most ``memory`` bytes of address space (RLIMIT_AS) and ``timeout`` seconds: a hang
    or a memory blow-up of the code under test ends its subprocess and fails the test, not the suite."""
    setup = f"import resource; resource.setrlimit(resource.RLIMIT_AS, ({memory}, {memory}))\n"
    try:
        return subprocess.run(
            [sys.executable, "-c", setup + code], capture_output=True, text=True, timeout=timeout, env=dict(os.environ)
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"still running after {timeout} s: {code}")


def commands(*argvs, timeout: float = 300) -> list:
    """``[(exit status, stderr)]`` of each ``pusupu`` command line of ``argvs``, run by ``cli.main`` one after the other
    in one :func:`limited` subprocess (the imports paid once); an exception out of ``main`` is status 1 and its
    traceback, as Python would end the command."""
    r = limited(
        f"""
import contextlib, io, json, traceback
from pusupu_jax.cli import cli
out = []
for argv in {[[str(a) for a in argv] for argv in argvs]!r}:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = cli.main(argv)
        except SystemExit as e:
            status = e.code
        except Exception:
            status = 1
            traceback.print_exc()
    out.append((status, err.getvalue()))
print(json.dumps(out))
""",
        timeout,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.splitlines()[-1])


def pusupu(*args, timeout: float = 300) -> tuple:
    """``(exit status, stderr)`` of one ``pusupu`` command (:func:`commands`)."""
    return commands(args, timeout=timeout)[0]


def one_line_exit_2(result: tuple, *expected: str) -> str:
    """The error line of a command (``(exit status, stderr)``) that had to end with one line and exit status 2,
    holding each of ``expected``."""
    status, err = result
    lines = err.splitlines()
    assert status == 2 and len(lines) == 1 and lines[0].startswith("pusupu: error: "), err[-3000:]
    assert "Traceback" not in err and all(e in lines[0] for e in expected), lines[0]
    return lines[0]


def special(tmp_path, kind: str):
    """A path under ``tmp_path`` holding a ``kind`` of file that is not a regular file (and what identifies it)."""
    path = tmp_path / f"{kind}.out"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "socket":
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(path))
        s.close()
    elif kind == "device":
        if not ROOT:
            pytest.skip("only root makes device nodes")
        os.mknod(path, stat.S_IFCHR | 0o600, os.makedev(1, 3))  # a character device like the system's null
    elif kind == "folder":
        path.mkdir()
    elif kind == "symlink":
        (tmp_path / "target").write_text("the target's own text\n")
        path.symlink_to(tmp_path / "target")
    return path


def same_node(path, kind: str) -> bool:
    st = os.lstat(path)
    return {
        "fifo": stat.S_ISFIFO,
        "socket": stat.S_ISSOCK,
        "device": stat.S_ISCHR,
        "folder": stat.S_ISDIR,
        "symlink": stat.S_ISLNK,
    }[kind](st.st_mode) and (kind != "symlink" or Path(os.readlink(path)).read_text() == "the target's own text\n")


@pytest.mark.parametrize("kind", ["fifo", "socket", "device", "folder", "symlink"])
def test_only_a_regular_file_is_ever_replaced(tmp_path, kind):
    """Every output (gain, ROS, report, plot, checkpoint, summary files) goes through files.write_atomic: it renamed
    its temporary over whatever stood at the path, a device node or FIFO included, and over a symlink instead of
    refusing it.  Now anything but a regular file is refused, left as it is, and no temporary is left behind."""
    path = special(tmp_path, kind)
    with pytest.raises(ParameterError, match="expected a regular file to write .or nothing., found a"):
        write_atomic(path, b"\x89PNG")
    assert same_node(path, kind)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_a_plot_onto_a_device_ends_in_one_line_before_any_work(tmp_path):
    """``--plot /dev/null`` as root replaced the device node with a PNG.  A device node made here (a FIFO where the
    suite does not run as root) is refused before the analysis, and stays."""
    kind = "device" if ROOT else "fifo"
    path = special(tmp_path, kind)
    one_line_exit_2(pusupu("analyze", "--plot", path), "--plot: ", "expected a regular file to write")
    assert same_node(path, kind)


@pytest.fixture(scope="module")
def gain_file(tmp_path_factory):
    """A valid gain file (Table 1, imc mode), its bytes."""
    from pusupu_jax import LoopRates, ServoParams, gains
    from pusupu_jax.hybrid import HybridGains

    path = gains.write(
        tmp_path_factory.mktemp("gains") / "gains.yaml",
        ServoParams.table1(),
        HybridGains(),
        LoopRates(n_mech=5),
        mode="imc",
    )
    return path.read_bytes()


def test_gains_sign_keeps_the_mode_and_refuses_a_symlink(tmp_path, gain_file):
    """``gains sign`` turned a 0600 file into 0644 and replaced a symlink by a file.  A file written again keeps its
    permission bits (and, written by root, its owner); a symlink as output is refused, the link and its target left
    as they were."""
    private = tmp_path / "private.yaml"
    private.write_bytes(gain_file)
    private.chmod(0o600)
    if ROOT:  # a user's file signed by root stays the user's
        os.chown(private, 4321, 4321)
    (tmp_path / "target").write_bytes(gain_file)
    link = tmp_path / "link.yaml"
    link.symlink_to(tmp_path / "target")
    signed, refused = commands(["gains", "sign", private], ["gains", "sign", link])
    assert signed[0] == 0, signed[1]
    assert stat.S_IMODE(private.stat().st_mode) == 0o600 and private.read_bytes() != gain_file  # signed anew
    assert not ROOT or (private.stat().st_uid, private.stat().st_gid) == (4321, 4321)
    one_line_exit_2(refused, "link.yaml: expected a regular file to write", "a symlink")
    assert link.is_symlink() and (tmp_path / "target").read_bytes() == gain_file


def test_a_new_file_gets_the_umask_mode(tmp_path):
    old = os.umask(0o027)
    try:
        path = write_atomic(tmp_path / "new.txt", "text")
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o640


def test_every_loader_refuses_a_fifo_without_blocking(tmp_path):
    """A FIFO given as ``--params``, a gain file, a tune configuration or a job file blocked its reader forever.  The
    one reader (inputs.read_text) now stats the path, opens it without blocking and refuses anything but a regular
    file: every loader, in a subprocess that may not hang."""
    fifo = tmp_path / "input.yaml"
    os.mkfifo(fifo)
    r = limited(f"""
from pusupu_jax import gains
from pusupu_jax.params_file import load_params_file
from pusupu_jax.params import ParameterError
from pusupu_jax.tune.config import TuneConfig
from pusupu_jax.tune import jobfile
for load in (load_params_file, gains.load, gains.sign, TuneConfig.load, jobfile.read):
    try:
        load({str(fifo)!r})
    except ParameterError as e:
        print(e)
""")
    lines = r.stdout.splitlines()
    assert r.returncode == 0 and len(lines) == 5, r.stderr[-3000:]
    assert all(line.startswith(f"{fifo}: expected a ") and line.endswith(", got a FIFO") for line in lines), lines


@pytest.mark.parametrize("kind", ["fifo", "socket", "device", "folder"])
def test_params_that_are_not_a_regular_file_end_in_one_line(tmp_path, kind):
    path = special(tmp_path, kind)
    one_line_exit_2(pusupu("sim", "--params", path), f"{path}: expected a YAML file, got a")


def test_an_input_larger_than_its_limit_is_refused_before_it_is_read(tmp_path):
    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.truncate(inputs.MAX_FILE_BYTES + 1)  # sparse: its size says it all
    with pytest.raises(ParameterError, match="at most 1024 KiB, got a larger file"):
        inputs.read_text(big, "YAML file", ParameterError)


def test_echoed_values_are_cut_and_escaped(tmp_path):
    """A 500 kB value came back as a 500 kB error line, and newlines in names were printed raw (a path, a job's
    name).  Every error is one line: echoed values cut to a few hundred characters, control characters escaped."""
    value, key, named = tmp_path / "value.yaml", tmp_path / "key.yaml", tmp_path / "new\nline.yaml"
    value.write_text("rates: {method: '" + "A" * 500_000 + "'}\n")
    key.write_text('rates: {"f_cur\\nrent\\u001b[31m": 5}\n')
    long, control, newline = commands(*(["sim", "--params", path] for path in (value, key, named)))
    line = one_line_exit_2(long, "rates.method: expected one of ('tustin', 'zoh'), got 'AAA", "... (500002 characters)")
    assert len(line) < 1000
    one_line_exit_2(control, r"unknown key 'f_cur\nrent\x1b[31m'")
    one_line_exit_2(newline, r"new\nline.yaml: cannot read YAML file")
    assert inputs.one_line("a\nb\tc\u202ed") == r"a\nb\tc\u202ed"
    assert inputs.shown("x" * 1000).endswith("... (1002 characters)") and len(inputs.shown("x" * 1000)) < 250


def test_a_job_named_with_a_newline_is_reported_on_one_line(tmp_path):
    """A scenario whose name fails its check names its failed job: that name was printed raw."""
    job = tmp_path / "job.yaml"
    job.write_text('scenarios: [{name: "two\\nlines", trajectory: p2p}]\n')
    status, err = pusupu("batch", job, "--out", tmp_path / "out")
    errors = [line for line in err.splitlines() if line.startswith("pusupu")]
    assert status == 1 and errors == [
        r"pusupu: job two\nlines: failed: scenarios[0].name: expected letters, digits "
        r"and - _ . / (not first: .), got 'two\nlines'"
    ], err[-3000:]


@pytest.mark.parametrize("kind", ["symlink", "fifo", "device", "hard link"])
def test_a_planted_lock_file_is_refused_and_its_target_untouched(tmp_path, kind):
    """A symlink planted as ``DIR/.pusupu.lock`` made ``tune`` truncate its target (open 'a+', then truncate).  The
    lock is opened without following a symlink or truncating, and must be a regular file of one link."""
    from pusupu_jax.tune.job import OutputLock

    out = tmp_path / "out"
    out.mkdir()
    lock = out / ".pusupu.lock"
    if kind == "hard link":
        (tmp_path / "target").write_text("the target's own text\n")
        os.link(tmp_path / "target", lock)
    else:
        special(tmp_path, kind).rename(lock)
    with pytest.raises(
        ParameterError,
        match=r"\.pusupu\.lock: expected a (regular file to write \(or nothing\)|lock "
        r"file of one link), found (a symlink|a FIFO|a character device|2 hard "
        r"links)",
    ):
        OutputLock(out)
    if kind == "hard link":
        assert (tmp_path / "target").read_text() == "the target's own text\n" and lock.stat().st_nlink == 2
    else:
        assert same_node(lock, kind)


def test_the_lock_is_still_exclusive_and_names_its_holder(tmp_path):
    from pusupu_jax.tune.job import OutputLock

    first = OutputLock(tmp_path)
    try:
        with pytest.raises(ParameterError, match=f"in use by another pusupu tune \\(pid {os.getpid()} on "):
            OutputLock(tmp_path)
    finally:
        first.release()
    OutputLock(tmp_path).release()
    assert stat.S_ISREG(os.lstat(tmp_path / ".pusupu.lock").st_mode)


# A tiny optimisation whose checkpoints are crafted below: the imc gains' log-parameters, a quadratic objective.
OPTIMISATION = """
from pusupu_jax.runtime import setup_jax
setup_jax()
import jax.numpy as jnp
from pusupu_jax import ServoParams
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import ParameterError
from pusupu_jax.tune.optimise import optimise
from pusupu_jax.tune.space import Space

space = Space.create(("imc",), ServoParams.table1(), HybridGains())


def vg(z):
    return (sum(jnp.sum(v ** 2) for v in z.values()), None), {k: 2 * v for k, v in z.items()}


def resume(path, digest="d", value_and_grad=vg):
    return optimise(value_and_grad, space.z0(), space.project, iterations=4, learning_rate=0.1, checkpoint=path,
                    checkpoint_every=2, digest=digest)
"""


@pytest.fixture(scope="module")
def optimisation():
    namespace = {}
    exec(OPTIMISATION, namespace)
    return namespace


@pytest.fixture(scope="module")
def finished(optimisation, tmp_path_factory):
    """The bytes of the checkpoint of a finished run of :data:`OPTIMISATION`."""
    path = tmp_path_factory.mktemp("checkpoint") / "checkpoint.npz"
    optimisation["resume"](path)
    return path.read_bytes()


def npy(array=None, *, descr: str = "", shape=(), data: bytes = b"") -> bytes:
    """An .npy file: ``array``'s, or a bare header (``descr``, ``shape``) followed by ``data``."""
    buffer = io.BytesIO()
    if array is not None:
        np.save(buffer, array)
    else:
        np.lib.format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False, "shape": shape})
        buffer.write(data)
    return buffer.getvalue()


def rezip(data: bytes, drop=(), add=None, meta=None) -> bytes:
    """The checkpoint ``data`` without the members ``drop``, with ``add`` ({name: .npy bytes}, deflated) and with
    ``meta``'s keys set (None: removed)."""
    add = add or {}
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(out, "w") as dst:
        for name in src.namelist():
            if name in drop or name in add:
                continue
            body = src.read(name)
            if name == "meta.npy" and meta:
                doc = json.loads(bytes(np.load(io.BytesIO(body))).decode()) | meta
                text = json.dumps({k: v for k, v in doc.items() if v is not None})
                body = npy(np.frombuffer(text.encode(), np.uint8))
            dst.writestr(name, body)
        for name, body in add.items():
            dst.writestr(name, body, compress_type=zipfile.ZIP_DEFLATED)
    return out.getvalue()


def zip_bomb(name: str, header: bytes, mib: int) -> bytes:
    """A zip of one member ``name``: ``header`` then ``mib`` MiB of zeros, deflated to about a thousandth (1 MiB of
    zeros compressed once, each piece ending in a full flush so that it stands alone, then repeated)."""
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    stream = c.compress(header) + c.flush(zlib.Z_FULL_FLUSH)
    stream += (c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH)) * mib + c.flush()
    size, n = len(header) + (mib << 20), name.encode()
    local = struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, 8, 0, 0x21, 0, len(stream), size, len(n), 0) + n
    central = (
        struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, 8, 0, 0x21, 0, len(stream), size, len(n), 0, 0, 0, 0, 0, 0)
        + n
    )
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, 1, 1, len(central), len(local) + len(stream), 0)
    return local + stream + central + end


def test_crafted_checkpoints_end_in_one_line_without_loading_them(tmp_path, finished):
    """A 5.8 MB zip bomb as checkpoint.npz took ``tune`` past 4 GB in 18 s, read before the configuration's check.
    Now the file's size, then ``meta`` and the configuration's digest, then every member's declared size, shape and
    dtype are checked before any array is loaded; every crafted checkpoint ends in one ParameterError.  Loaded in a
    subprocess of at most 3 GiB, as ``tune`` resumes."""
    lambda1 = zipfile.ZipFile(io.BytesIO(finished)).read("best/lambda1.npy")
    shape = np.load(io.BytesIO(lambda1)).shape
    bomb = npy(descr="|u1", shape=(3800 << 20,))
    cases = {
        "bomb": (zip_bomb("meta.npy", bomb, 3800), "expected a pusupu checkpoint of at most"),
        "small bomb": (
            rezip(finished, add={"best/lambda1.npy": npy(descr="<f8", shape=(5 << 20,), data=bytes(40 << 20))}),
            "best/lambda1.npy' declares 41943168 bytes, expected at most",
        ),
        "meta's header": (
            rezip(finished, add={"meta.npy": npy(descr="|u1", shape=(4 << 30,), data=b"{}")}),
            "meta: expected at most",
        ),
        "member name": (rezip(finished, add={"evil.npy": npy(np.zeros(3))}), "unexpected member 'evil.npy'"),
        "shape": (
            rezip(finished, add={"best/lambda1.npy": npy(np.zeros(7))}),
            f"best/lambda1: expected float64 of shape {shape}, got float64 of shape (7,)",
        ),
        "dtype": (
            rezip(finished, add={"best/lambda1.npy": npy(np.zeros(shape, np.float32))}),
            "best/lambda1: expected float64",
        ),
        "object array": (
            rezip(finished, add={"best/lambda1.npy": npy(descr="|O", shape=shape, data=b"\x80\x04N.")}),
            "an object array, expected numbers",
        ),
        "a missing key": (rezip(finished, meta={"history": None}), "meta: missing key 'history'"),
        "a key's kind": (rezip(finished, meta={"iteration": "4"}), "meta.iteration: expected an integer, got str"),
        "an entry": (
            rezip(finished, meta={"history": [[{"start": 0}]]}),
            "meta.history[0][0]: missing key 'iteration'",
        ),
        "a number past float's range": (
            rezip(finished, meta={"best_value": [10**400]}),
            "not a pusupu checkpoint (int too large to convert to float)",
        ),
        "nesting": (
            rezip(finished, add={"meta.npy": npy(np.frombuffer(b"[" * 5000, np.uint8))}),
            "not a pusupu checkpoint (maximum recursion depth exceeded",
        ),
        "another configuration": (
            rezip(finished, meta={"digest": "e"}, add={"best/lambda1.npy": bomb}),
            "checkpoint of another configuration (hash 'e', this one d)",
        ),
        "not a zip": (b"\x80\x04N.", "not a pusupu checkpoint (File is not a zip file)"),
    }
    for name, (data, _) in cases.items():
        (tmp_path / f"{name}.npz").write_bytes(data)
    os.mkfifo(tmp_path / "fifo.npz")
    cases["fifo"] = (None, "expected a pusupu checkpoint, got a FIFO")
    r = limited(
        OPTIMISATION
        + f"""
for name in {list(cases)!r}:
    try:
        resume({str(tmp_path)!r} + f"/{{name}}.npz")
    except ParameterError as e:
        print(name, "|", e)
    else:
        print(name, "| resumed")
"""
    )
    assert r.returncode == 0, r.stderr[-3000:]
    got = dict(line.split(" | ", 1) for line in r.stdout.splitlines())
    for name, (_, message) in cases.items():
        assert message in got[name], (name, got[name])
        assert got[name].endswith(("; delete it or use --fresh", "; use --fresh or another --out")), got[name]


def test_a_finished_checkpoint_missing_a_field_is_refused_before_anything_is_exported(optimisation, finished, tmp_path):
    """A finished checkpoint missing one best value resumed to a result holding the start value for it, which the
    tuner exported marked as tuned (and then crashed).  Each group of arrays must be whole."""
    path = tmp_path / "checkpoint.npz"
    path.write_bytes(rezip(finished, drop=("best/lambda2.npy",)))

    def never(z):
        raise AssertionError("a finished run is not evaluated again")

    with pytest.raises(
        ParameterError,
        match=r"not a pusupu checkpoint \(best/lambda2 missing\); delete it or use "
        r"--fresh",
    ):
        optimisation["resume"](path, value_and_grad=never)
    path.write_bytes(rezip(finished, drop=[f"best/{k}.npy" for k in ("lambda1", "lambda2", "T0")]))
    with pytest.raises(ParameterError, match="missing arrays: best"):
        optimisation["resume"](path, value_and_grad=never)
    path.write_bytes(finished)
    assert set(optimisation["resume"](path, value_and_grad=never).z) == {"lambda1", "lambda2", "T0"}


def test_ros_joint_names_are_checked_with_the_tune_config(tmp_path):
    """A joint name the ROS exporter refuses passed the tune configuration, and the run failed only at its export.
    The configuration now applies the exporter's own rule, before any work."""
    from pusupu_jax.tune.config import TuneConfig

    config = tmp_path / "tune.yaml"
    config.write_text("ros_joints: [slide 1, slide_2, slide_3, slide_4, slide_5, slide_6]\n")
    with pytest.raises(
        ParameterError,
        match=r"tune config ros_joints: expected 6 distinct names of letters, digits "
        r"and _, got \('slide 1', ",
    ):
        TuneConfig.load(config)


@pytest.mark.parametrize("refused", ["joint names", "a FIFO among the outputs"])
def test_the_export_writes_every_file_or_none(tmp_path, refused):
    """The export wrote gains.yaml, then failed on the ROS files: a new gains.yaml beside the old ROS files, and a
    report saying that no gain file was written.  Now every file is made and every path checked first."""
    import dataclasses

    from pusupu_jax import ServoParams
    from pusupu_jax.hybrid import HybridGains
    from pusupu_jax.machine import machine_rates
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.job import export

    cfg = TuneConfig()
    old = {
        name: f"the earlier {name}\n"
        for name in ("gains.yaml", "ros2_pid_controller.yaml", "ros2_joint_trajectory_controller.yaml")
    }
    for name, text in old.items():
        (tmp_path / name).write_text(text)
    if refused == "joint names":  # a configuration made without its checks, as an older pusupu_jax's was
        cfg = dataclasses.replace(cfg, ros_joints=("slide 1",) + cfg.ros_joints[1:])
        message = "ROS joints: expected 6 distinct names"
    else:
        fifo = tmp_path / "ros2_joint_trajectory_controller.yaml"
        fifo.unlink()
        os.mkfifo(fifo)
        del old[fifo.name]
        message = "expected a regular file to write (or nothing), found a FIFO"
    report = export(tmp_path, cfg, ServoParams.table1(), HybridGains(), machine_rates(), ("lambda1",), {})
    assert report.exported == [] and message in report.error
    assert report.gains_file.left_as_it_was["path"] == str(tmp_path / "gains.yaml")
    assert {name: (tmp_path / name).read_text() for name in old} == old
    assert refused == "joint names" or stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    if refused == "joint names":  # with the default names, all three
        report = export(tmp_path, TuneConfig(), ServoParams.table1(), HybridGains(), machine_rates(), ("lambda1",), {})
        assert len(report.exported) == 3 and report.error is None


def test_a_tune_refuses_outputs_that_are_not_regular_files_before_any_work(tmp_path):
    """Every file ``tune`` writes into --out (gains, ROS files, report, plots, checkpoint) is checked before the lock
    is taken and anything compiles."""
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / "path_arc.png")
    line = one_line_exit_2(pusupu("tune", "--quick", "--out", out), "path_arc.png: expected a regular file to write")
    assert "a FIFO" in line and not (out / ".pusupu.lock").exists()


@pytest.fixture(scope="module")
def fast_rates(tmp_path_factory):
    """Parameter files with a 100 kHz current loop and the mechanics stepped at every tick (the fastest current loop
    a file may hold: 5 times the default's ticks per simulated second), and with a 1 MHz one, which no file may
    hold."""
    folder = tmp_path_factory.mktemp("rates")
    (folder / "params.yaml").write_text("rates: {f_current: 1.0e+5, n_velocity: 5, n_position: 4, n_mech: 1}\n")
    (folder / "mhz.yaml").write_text("rates: {f_current: 1.0e+6, n_velocity: 1000, n_position: 1000}\n")
    return folder


def test_every_duration_rate_and_horizon_is_bounded_by_its_work(tmp_path, fast_rates, gain_file):
    """``sim`` at 1 MHz for 2000 s ran unbounded (2e9 current-loop ticks), ``gains check-ros --seconds inf`` ended in a
    traceback, and a tune's iterations or windows and a job file's were bounded by nothing.  A file's loop rates are
    now bounded (100 kHz at most: the 1 MHz file is refused as it is read), and each run is checked against the work
    it implies (steps at the given rates, not seconds) before anything compiles, with one line that gives the limit.
    One subprocess runs every command."""
    params, mhz = fast_rates / "params.yaml", fast_rates / "mhz.yaml"
    (tmp_path / "gains.yaml").write_bytes(gain_file)
    (tmp_path / "tune.yaml").write_text("iterations: 100000\n")
    (tmp_path / "wide.yaml").write_text(f"kin_error_seeds: {list(range(100))}\n")
    (tmp_path / "job.yaml").write_text("tune: {iterations: 100000}\nscenarios: [{trajectory: p2p}]\n")
    cases = [
        (
            ["sim", "--params", params, "--duration", "2000"],
            "trajectory duration: expected at most 400 s at these rates (4e+07 current-loop ticks of 10 us), "
            "got 2000 s",
        ),
        (["sim", "--params", mhz], "rates: f_current is 1e+06 Hz; expected 1000 to 100000 Hz"),
        (
            ["gains", "check-ros", tmp_path / "gains.yaml", "--seconds", "inf"],
            "--seconds: expected a finite number, got inf",
        ),
        (
            ["tune", "--config", tmp_path / "tune.yaml", "--out", tmp_path / "tune"],
            "tune config: expected at most 5e+08 mechanical steps of the machine in all",
        ),
        (
            ["tune", "--config", tmp_path / "wide.yaml", "--out", tmp_path / "tune"],
            "tune config: expected at most 1e+06 mechanical steps of the machine in one gradient",
        ),
        (
            ["batch", tmp_path / "job.yaml", "--out", tmp_path / "batch"],
            "pusupu: job p2p: failed: its tuning work: expected at most 5e+08 mechanical steps",
        ),
    ]
    results = commands(*(argv for argv, _ in cases))
    for (argv, message), (status, err) in zip(cases, results):
        lines = [line for line in err.splitlines() if line.startswith("pusupu")]
        assert status == (1 if argv[0] == "batch" else 2) and len(lines) == 1 and message in lines[0], (argv, err)
    assert not (tmp_path / "tune").exists()


def test_the_work_limits_leave_the_defaults_far_inside():
    from pusupu_jax import LoopRates, workload
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.run import check_work

    workload.check_run("sim", 2000.0, LoopRates())  # the longest axis run the default rates always allowed
    workload.check_run("both paths, two controllers", 2 * 60.0, LoopRates(n_mech=5), machine=True)
    check_work(TuneConfig())
    check_work(TuneConfig().replace(iterations=250, starts=4))
    with pytest.raises(
        ParameterError,
        match=r"sim: expected at most 2000 s at these rates \(4e\+07 current-loop "
        r"ticks of 50 us\), got 2001 s",
    ):
        workload.check_run("sim", 2001.0, LoopRates())


@pytest.mark.parametrize(
    "values, field",
    [
        ("servo: {Kv: 1.0e+308}", "ServoParams.Kv"),
        ("servo: {lambda2: 1.0e-300}", "ServoParams.lambda2"),
        ("servo: {lead: 1.0e+300}", "ServoParams.lead"),
        ("servo: {Tw: 1.0e+5}", "ServoParams.Tw"),
        ("load: {mass: 1.0e+308}", "AxisLoad.mass"),
    ],
)
def test_absurd_parameters_end_in_one_line(tmp_path, values, field):
    """``analyze --params`` with these values ended in tracebacks from python-control and numpy.  Each field's
    documented range refuses them as the file is read: one line naming the file and the field, exit 2."""
    params = tmp_path / "params.yaml"
    params.write_text(values + "\n")
    [(status, err)] = commands(["analyze", "--params", params])
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and "Traceback" not in err, err[-3000:]
    assert lines[0].startswith(f"pusupu: error: {params}: {field}: expected "), lines[0]


def test_an_internal_error_keeps_its_traceback(monkeypatch):
    """Only the inputs' checks turn a ValueError into one line: raised in the work, it is a bug, and shows."""
    from pusupu_jax.cli import cli
    from pusupu_jax import analysis

    def broken(*args, **kwargs):
        raise ValueError("a bug in the analysis")

    monkeypatch.setattr(analysis, "loop_metrics", broken)
    with pytest.raises(ValueError, match="a bug in the analysis"):
        cli.main(["analyze"])
