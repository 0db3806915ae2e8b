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
from pusupu_jax.config import write_atomic
from pusupu_jax.params import ParameterError

ROOT = os.geteuid() == 0


def limited(code: str, timeout: float = 120, memory: int = 3 << 30) -> subprocess.CompletedProcess:
    """``python -c code`` with at most ``memory`` bytes of address space (RLIMIT_AS) and ``timeout`` seconds: a hang
    or a memory blow-up of the code under test ends its subprocess and fails the test, not the suite."""
    setup = f"import resource; resource.setrlimit(resource.RLIMIT_AS, ({memory}, {memory}))\n"
    try:
        return subprocess.run([sys.executable, "-c", setup + code], capture_output=True, text=True, timeout=timeout,
                              env=dict(os.environ))
    except subprocess.TimeoutExpired:
        pytest.fail(f"still running after {timeout} s: {code}")


def pusupu(*args, timeout: float = 120, memory: int = 3 << 30) -> subprocess.CompletedProcess:
    """The ``pusupu`` command in a :func:`limited` subprocess."""
    return limited(f"import runpy, sys; sys.argv = ['pusupu', *{[str(a) for a in args]!r}]; "
                   "runpy.run_module('pusupu_cli', run_name='__main__')", timeout, memory)


def one_line_exit_2(r: subprocess.CompletedProcess, *expected: str) -> str:
    """The error line of a command that had to end with one line and exit status 2, holding each of ``expected``."""
    lines = r.stderr.splitlines()
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("pusupu: error: "), r.stderr[-3000:]
    assert "Traceback" not in r.stderr and all(e in lines[0] for e in expected), lines[0]
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
    return {"fifo": stat.S_ISFIFO, "socket": stat.S_ISSOCK, "device": stat.S_ISCHR, "folder": stat.S_ISDIR,
            "symlink": stat.S_ISLNK}[kind](st.st_mode) and (
        kind != "symlink" or Path(os.readlink(path)).read_text() == "the target's own text\n")


@pytest.mark.parametrize("kind", ["fifo", "socket", "device", "folder", "symlink"])
def test_only_a_regular_file_is_ever_replaced(tmp_path, kind):
    """Every output (gain, ROS, report, plot, checkpoint, summary files) goes through config.write_atomic: it renamed
    its temporary over whatever stood at the path, a device node or FIFO included, and over a symlink instead of
    refusing it.  Now anything but a regular file is refused, left as it is, and no temporary is left behind."""
    path = special(tmp_path, kind)
    with pytest.raises(ParameterError, match=f"expected a regular file to write .or nothing., found a"):
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

    path = gains.write(tmp_path_factory.mktemp("gains") / "gains.yaml", ServoParams.table1(), HybridGains(),
                       LoopRates(n_mech=5), mode="imc")
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
    r = pusupu("gains", "sign", private)
    assert r.returncode == 0, r.stderr
    assert stat.S_IMODE(private.stat().st_mode) == 0o600 and private.read_bytes() != gain_file  # signed anew
    assert not ROOT or (private.stat().st_uid, private.stat().st_gid) == (4321, 4321)
    (tmp_path / "target").write_bytes(gain_file)
    link = tmp_path / "link.yaml"
    link.symlink_to(tmp_path / "target")
    one_line_exit_2(pusupu("gains", "sign", link), "link.yaml: expected a regular file to write", "a symlink")
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
from pusupu_jax.config import load_params_file
from pusupu_jax.params import ParameterError
from tune.config import TuneConfig
from tune import jobfile
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
    value = tmp_path / "value.yaml"
    value.write_text("rates: {method: '" + "A" * 500_000 + "'}\n")
    line = one_line_exit_2(pusupu("sim", "--params", value),
                           "rates.method: expected one of ('tustin', 'zoh'), got 'AAA", "... (500002 characters)")
    assert len(line) < 1000
    key = tmp_path / "key.yaml"
    key.write_text('rates: {"f_cur\\nrent\\u001b[31m": 5}\n')
    one_line_exit_2(pusupu("sim", "--params", key), r"unknown key 'f_cur\nrent\x1b[31m'")
    named = tmp_path / "new\nline.yaml"
    one_line_exit_2(pusupu("sim", "--params", named), r"new\nline.yaml: cannot read YAML file")
    assert inputs.one_line("a\nb\tc\u202ed") == r"a\nb\tc\u202ed"
    assert inputs.shown("x" * 1000).endswith("... (1002 characters)") and len(inputs.shown("x" * 1000)) < 250


def test_a_job_named_with_a_newline_is_reported_on_one_line(tmp_path):
    """A scenario whose name fails its check names its failed job: that name was printed raw."""
    job = tmp_path / "job.yaml"
    job.write_text('scenarios: [{name: "two\\nlines", trajectory: p2p}]\n')
    r = pusupu("batch", job, "--out", tmp_path / "out")
    errors = [line for line in r.stderr.splitlines() if line.startswith("pusupu")]
    assert r.returncode == 1 and errors == [r"pusupu: job two\nlines: failed: scenarios[0].name: expected letters, "
                                            r"digits and - _ . / (not first: .), got 'two\nlines'"], r.stderr[-3000:]


@pytest.mark.parametrize("kind", ["symlink", "fifo", "device", "hard link"])
def test_a_planted_lock_file_is_refused_and_its_target_untouched(tmp_path, kind):
    """A symlink planted as ``DIR/.pusupu.lock`` made ``tune`` truncate its target (open 'a+', then truncate).  The
    lock is opened without following a symlink or truncating, and must be a regular file of one link."""
    from tune.job import OutputLock

    out = tmp_path / "out"
    out.mkdir()
    lock = out / ".pusupu.lock"
    if kind == "hard link":
        (tmp_path / "target").write_text("the target's own text\n")
        os.link(tmp_path / "target", lock)
    else:
        special(tmp_path, kind).rename(lock)
    with pytest.raises(ParameterError, match=r"\.pusupu\.lock: expected a (regular file to write \(or nothing\)|lock "
                                             r"file of one link), found (a symlink|a FIFO|a character device|2 hard "
                                             r"links)"):
        OutputLock(out)
    if kind == "hard link":
        assert (tmp_path / "target").read_text() == "the target's own text\n" and lock.stat().st_nlink == 2
    else:
        assert same_node(lock, kind)


def test_the_lock_is_still_exclusive_and_names_its_holder(tmp_path):
    from tune.job import OutputLock

    first = OutputLock(tmp_path)
    try:
        with pytest.raises(ParameterError, match=f"in use by another pusupu tune \\(pid {os.getpid()} on "):
            OutputLock(tmp_path)
    finally:
        first.release()
    OutputLock(tmp_path).release()
    assert stat.S_ISREG(os.lstat(tmp_path / ".pusupu.lock").st_mode)
