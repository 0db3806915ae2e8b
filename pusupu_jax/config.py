"""Parameter files (YAML) and the JAX runtime set-up shared by the CLI, tests and benchmarks (host-side).

A parameter file has up to four sections, each optional; in ``servo`` and ``load`` a
scalar applies to every axis, a list gives one value per axis; SI units as documented in
``docs/parameters.md``::

    servo:   {lambda1: 0.018, Kv: [0.015, 0.015, 0.015, 0.015, 0.015, 0.02]}
    load:    {mass: 25.0, inclination: 1.5708}
    rates:   {f_current: 20000, n_velocity: 5, n_position: 4, method: tustin}
    hybrid:  {m6: 0.1, c6: 1000.0, g: 100.0, form: signed}   # eq. 14, machine-wide scalars
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import stat
import tempfile
from pathlib import Path
from typing import NamedTuple

from . import inputs
from .hybrid import HybridGains
from .params import AxisLoad, LoopRates, ParameterError, ServoParams
from .stability import check_rates

SECTIONS = ("servo", "load", "rates", "hybrid")

# jaxlib 0.10.2 on CPU: vmapped rollouts of 768 or more parameter sets wedge XLA's thread
# pool (every worker idle, the caller waiting forever; 5 of 5 runs hung here).  Turning off
# the concurrency-optimised scheduler avoids it (0 of 8 hung, batches 768-4096).  The flag
# must be in XLA_FLAGS before the CPU backend starts, so the package applies it on import.
XLA_CPU_WORKAROUND = "--xla_cpu_enable_concurrency_optimized_scheduler=false"

# XLA's CPU compiler, jaxlib 0.10.2: the MLIR fusion emitters and LLVM's expensive passes cost
# compile time and, on these programs, buy no speed.  Measured on the 2-core CPU, compile from an
# empty cache then the compiled call (benchmarks/bench_cold_start.py --xla-flags, and the contact
# gradient of tests/test_mjx_plant.py): the contact gradient 49.9 -> 29.2 s to compile, 0.50 -> 0.35 s
# a call; the default tune's forward pass 26.4 -> 20.2 s to compile, its gradient 85-86 s either way
# and 13.0 -> 11.3 s a call.  The LLVM flag also reaches a GPU's code generator, which was not
# measured: it is added only when no GPU plugin for jax is installed.
XLA_CPU_COMPILE = ("--xla_cpu_use_fusion_emitters=false",)
XLA_LLVM_CPU_ONLY = ("--xla_llvm_disable_expensive_passes=true",)
# A jaxlib that does not know a flag in XLA_FLAGS aborts the process when its backend starts ("Unknown flag in
# XLA_FLAGS"): jaxlib 0.11.2 (seen with a GPU plugin) has no --xla_cpu_use_fusion_emitters.  So the
# compile flags are added only for the jaxlib series they were measured with; the thread-pool workaround, whose flag
# 0.11.2 knows too, for every jaxlib.
XLA_COMPILE_MEASURED_ON = ("0.10.",)
# The bridge's and the simulated robot's processes (hw_bridge) run small compiled steps at a fixed rate on one CPU:
# XLA's multi-threaded Eigen hands parts of them to its pool threads, whose wake-ups cost more than they save.  The
# simulated robot's command, timed in its real-time process at 1 kHz (jaxlib 0.10.2): p50 240 us either way, p99 719
# -> 305 us, max 3.3 -> 0.56 ms.  Added for those processes only (apply_xla_workaround(one_thread=True)), and, as the
# compile flags, only with a jaxlib of the series it was measured with.
XLA_CPU_ONE_THREAD = ("--xla_cpu_multi_thread_eigen=false",)


def _gpu_plugin_installed() -> bool:
    """Whether a GPU plugin for jax (``jax_plugins.xla_cuda12`` and the like) is installed; nothing is imported."""
    import importlib.util
    import pkgutil

    spec = importlib.util.find_spec("jax_plugins")
    return spec is not None and any(True for _ in pkgutil.iter_modules(spec.submodule_search_locations or []))


def _jaxlib_version() -> str:
    """The installed jaxlib's version ('' when none is installed); nothing is imported."""
    import importlib.metadata

    try:
        return importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return ""


def apply_xla_workaround(one_thread: bool = False) -> None:
    """Add :data:`XLA_CPU_WORKAROUND` and, with a jaxlib of :data:`XLA_COMPILE_MEASURED_ON`, the compile-time flags
    (:data:`XLA_CPU_COMPILE`; :data:`XLA_LLVM_CPU_ONLY` where no GPU plugin is installed) to ``XLA_FLAGS``, each
    unless the user set that flag themselves.  ``one_thread``: :data:`XLA_CPU_ONE_THREAD` too, for a real-time
    process; it takes effect only when called before JAX's CPU backend starts (the process's first computation).

    ``PUSUPU_XLA_WORKAROUND=0`` leaves ``XLA_FLAGS`` alone (for a jaxlib that no longer knows the flags).
    """
    if os.environ.get("PUSUPU_XLA_WORKAROUND") == "0":
        return
    wanted = (XLA_CPU_WORKAROUND,)
    if _jaxlib_version().startswith(XLA_COMPILE_MEASURED_ON):
        wanted += (*XLA_CPU_COMPILE, *(() if _gpu_plugin_installed() else XLA_LLVM_CPU_ONLY),
                   *(XLA_CPU_ONE_THREAD if one_thread else ()))
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in wanted:
        if flag.split("=")[0] not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags


class ParamsFile(NamedTuple):
    """A parameter file's sections, each at its defaults where the file leaves it out."""

    servo: ServoParams
    load: AxisLoad
    rates: LoopRates
    hybrid: HybridGains


def load_params_file(path=None) -> ParamsFile:
    """Read and validate a parameter file (None: every default); raises :class:`ParameterError` naming the problem."""
    if path is None:
        return ParamsFile(ServoParams.table1(), AxisLoad.default(), LoopRates(), HybridGains())
    path = Path(path)
    data = read_yaml_mapping(path, "section", SECTIONS)
    try:
        return ParamsFile(*(parse({} if data.get(name) is None else data[name]) for name, parse in (
            ("servo", ServoParams.from_mapping), ("load", AxisLoad.from_mapping), ("rates", rates_from_mapping),
            ("hybrid", HybridGains.from_mapping))))
    except ParameterError as e:
        raise ParameterError(f"{path}: {e}") from None


def read_yaml_mapping(path: Path, what: str, keys, error=ParameterError) -> dict:
    """A YAML file holding a mapping whose keys are among ``keys`` (empty file: ``{}``).

    Read with :func:`pusupu_jax.inputs.read_yaml` (size limit, UTF-8, no aliases, no duplicate
    keys); raises ``error`` with the path and one line saying what is wrong (an unknown key is
    called a ``what`` in the message).
    """
    data = inputs.read_yaml(path, "YAML file", error)
    return inputs.check_keys({} if data is None else data, str(path), keys, error, what=what)


def umask() -> int:
    """The process's file-creation mask (read without changing it where the OS allows)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_output(path) -> os.stat_result | None:
    """What stands at ``path``, an output about to be written: nothing (None) or a regular file (its ``lstat``).

    Anything else (a symlink, folder, FIFO, socket or device node) raises :class:`ParameterError` in one line and is
    left as it is: a rename over it would replace the node itself (as root, ``--plot /dev/null`` replaced the device
    with a PNG), and a symlink is not followed to whatever it names.
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    if not stat.S_ISREG(st.st_mode):
        raise ParameterError(f"{path}: expected a regular file to write (or nothing), found "
                             f"{inputs.file_kind(st.st_mode)}; left as it is")
    return st


def write_files(files: dict) -> list[Path]:
    """Write ``{path: data}`` (str or bytes) atomically, every file or none as far as the file system allows.

    Every path is checked first (:func:`check_output`); then each file's data goes to a temporary file in its
    folder, synced; then, every path checked again, each temporary is renamed over its path.  A reader sees an old
    file or a new one, never a part; a failure before the renames (a full disk included) leaves every old file and no
    temporary behind.  A new file gets the mode a plain ``open`` would give it (``0666`` less the umask: ``0644``
    under the usual ``022``); a file written again keeps its permission bits (not a set-user or set-group ID) and,
    where the process may give it away (root), its owner and group.
    """
    items = [(Path(path), data.encode() if isinstance(data, str) else data) for path, data in files.items()]
    temps = []
    try:
        for path, data in items:
            old = check_output(path)
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
            temps.append(tmp)
            with os.fdopen(fd, "wb") as f:
                if old is not None and (old.st_uid, old.st_gid) != (os.geteuid(), os.getegid()):
                    with contextlib.suppress(PermissionError):  # only root may give a file away
                        os.fchown(fd, old.st_uid, old.st_gid)
                os.fchmod(fd, 0o666 & ~umask() if old is None else stat.S_IMODE(old.st_mode) & 0o777)
                f.write(data)
                f.flush()
                os.fsync(fd)
        for path, _ in items:
            check_output(path)
        for (path, _), tmp in zip(items, temps):
            os.replace(tmp, path)
    finally:
        for tmp in temps:
            if os.path.exists(tmp):
                os.unlink(tmp)
    return [path for path, _ in items]


def write_atomic(path, data: str | bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`write_files`: a regular file or nothing at ``path``, its mode
    kept)."""
    return write_files({path: data})[0]


def rates_from_mapping(values) -> LoopRates:
    """A :class:`LoopRates` from a mapping of its fields (a params file's or gain file's ``rates``), checked: each
    field of its kind, and each loop's rate in its range (:func:`pusupu_jax.stability.check_rates`)."""

    where = "rates"
    inputs.check_keys(values, where, [f.name for f in dataclasses.fields(LoopRates)], ParameterError)
    out = dict(values)
    if "f_current" in out:
        out["f_current"] = inputs.number(out["f_current"], f"{where}.f_current", ParameterError, low=0.0,
                                         low_open=True)
    for name in ("n_velocity", "n_position", "n_mech"):
        if name in out:
            out[name] = inputs.integer(out[name], f"{where}.{name}", ParameterError, low=1, high=1000)
    if "method" in out:
        inputs.choice(out["method"], f"{where}.method", ("tustin", "zoh"), ParameterError)
    rates = LoopRates(**out)
    check_rates(rates)
    return rates


def setup_jax(cache_dir: str | os.PathLike | None = None, x64: bool = True) -> Path:
    """Enable float64 and JAX's persistent compilation cache (every compiled function is kept).

    The cache lives in ``cache_dir``, else ``$PUSUPU_JAX_CACHE``, else JAX's own
    ``$JAX_COMPILATION_CACHE_DIR``, else ``~/.cache/pusupu_jax/jax``.  Returns the cache directory.
    """
    import jax

    path = Path(cache_dir or os.environ.get("PUSUPU_JAX_CACHE") or os.environ.get("JAX_COMPILATION_CACHE_DIR")
                or Path.home() / ".cache" / "pusupu_jax" / "jax")
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_enable_x64", x64)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return path
