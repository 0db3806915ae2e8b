"""The JAX runtime set-up of the entry points (the CLI, the tests' conftest, the benchmarks, a notebook's first
cell): XLA's flags, float64 and the persistent compilation cache (host-side).

:func:`apply_xla_workaround` runs on ``import pusupu_jax`` (the flags must be in ``XLA_FLAGS`` before JAX's
backend starts; ``PUSUPU_XLA_WORKAROUND=0`` opts out); :func:`setup_jax` changes JAX's configuration and is
called by entry points only.
"""

from __future__ import annotations

import os
from pathlib import Path

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
# jaxlib 0.11.2 gets none: --xla_llvm_disable_expensive_passes=true, on 2 and 14 pinned cores of one 16-core H200 host,
# with and without it alternating over two rounds, ran the default tune's gradient iterations 2 % slower on 2 cores and
# 5 % faster on 14, and its cold first iteration 4 % slower on 2 (docs/benchmarks.md), and left the GPU's as they were.
XLA_COMPILE_MEASURED_ON = ("0.10.",)
# The bridge's and the simulated robot's processes (hw_bridge) run small compiled steps at a fixed rate on one CPU:
# XLA's multi-threaded Eigen hands parts of them to its pool threads, whose wake-ups cost more than they save.  The
# simulated robot's command, timed in its real-time process at 1 kHz (jaxlib 0.10.2): p50 240 us either way, p99 719
# -> 305 us, max 3.3 -> 0.56 ms.  Added for those processes only (apply_xla_workaround(one_thread=True)), and, as the
# compile flags, only with a jaxlib of the series it was measured with.
XLA_CPU_ONE_THREAD = ("--xla_cpu_multi_thread_eigen=false",)
# One XLA host device per CPU the process may run on: independent rows of a batch (the tuner's windows, the paths of
# its forward pass) are laid over them (pusupu_jax.devices.row_mesh) and run on every core together; one device
# computes a scan of small steps on one core.  Every jaxlib knows the flag.  Not for the real-time processes
# (one_thread).
XLA_HOST_DEVICES = "--xla_force_host_platform_device_count"


# numpy's and scipy's linear algebra (OpenBLAS) starts a thread per CPU, and its threads wait for work spinning: beside
# XLA's own threads, and on a machine that other processes share, they burn the CPU that the computation needs.
# `pusupu identify` of tests/test_identify.py's Coulomb case (a 0.8 s window and the step check; the compile cache
# warm; 2-core AMD EPYC): alone 59 -> 51 s (83 -> 54 s of CPU) with one thread; beside two busy processes 400 ->
# 75-85 s.  The count is read when numpy loads OpenBLAS, so the package sets it on import, before numpy's (a count the
# user set stays).
BLAS_THREADS = "OPENBLAS_NUM_THREADS"


def limit_blas_threads() -> None:
    """One OpenBLAS thread (:data:`BLAS_THREADS`) unless the user set a count; effective only before numpy's import."""
    os.environ.setdefault(BLAS_THREADS, "1")


def cpu_count() -> int:
    """The CPUs this process may run on (its affinity, as ``taskset`` sets it), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity on this OS
        return max(1, os.cpu_count() or 1)


def gpu_plugin_installed() -> bool:
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


_host_devices_added = False  # whether apply_xla_workaround put XLA_HOST_DEVICES into XLA_FLAGS (not the user)


def apply_xla_workaround(one_thread: bool = False) -> None:
    """Add :data:`XLA_CPU_WORKAROUND`, one host device per CPU (:data:`XLA_HOST_DEVICES`; ``one_thread`` takes it
    out again where this function put it in)
    and, with a jaxlib of :data:`XLA_COMPILE_MEASURED_ON`, the compile-time flags
    (:data:`XLA_CPU_COMPILE`; :data:`XLA_LLVM_CPU_ONLY` where no GPU plugin is installed) to ``XLA_FLAGS``, each
    unless the user set that flag themselves.  ``one_thread``: :data:`XLA_CPU_ONE_THREAD` too, for a real-time
    process; it takes effect only when called before JAX's CPU backend starts (the process's first computation).

    ``PUSUPU_XLA_WORKAROUND=0`` leaves ``XLA_FLAGS`` alone (for a jaxlib that no longer knows the flags).
    """
    global _host_devices_added
    if os.environ.get("PUSUPU_XLA_WORKAROUND") == "0":
        return
    flags = os.environ.get("XLA_FLAGS", "")
    if one_thread and _host_devices_added:  # the package's import added it: a real-time process runs on one CPU
        flags = _without_host_devices(flags)
    elif not one_thread and XLA_HOST_DEVICES not in flags:
        flags = f"{flags} {XLA_HOST_DEVICES}={cpu_count()}".strip()
        _host_devices_added = True
    wanted: tuple[str, ...] = (XLA_CPU_WORKAROUND,)
    if _jaxlib_version().startswith(XLA_COMPILE_MEASURED_ON):
        wanted += (
            *XLA_CPU_COMPILE,
            *(() if gpu_plugin_installed() else XLA_LLVM_CPU_ONLY),
            *(XLA_CPU_ONE_THREAD if one_thread else ()),
        )
    for flag in wanted:
        if flag.split("=")[0] not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags


def xla_flags_for(cpus: int) -> str:
    """``XLA_FLAGS`` for a worker process that computes on ``cpus`` CPUs (a Ray task): the one host device per CPU
    that :func:`apply_xla_workaround` added replaced by ``cpus`` of them (a count the user set stays)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if not _host_devices_added:
        return flags
    return f"{_without_host_devices(flags)} {XLA_HOST_DEVICES}={cpus}".strip()


def _without_host_devices(flags: str) -> str:
    """``flags`` without :data:`XLA_HOST_DEVICES`."""
    return " ".join(f for f in flags.split() if not f.startswith(XLA_HOST_DEVICES + "="))


def setup_jax(cache_dir: str | os.PathLike[str] | None = None, x64: bool = True, synchronous_cpu: bool = False) -> Path:
    """Enable float64 and JAX's persistent compilation cache (every compiled function is kept).

    The cache lives in ``cache_dir``, else ``$PUSUPU_JAX_CACHE``, else JAX's own
    ``$JAX_COMPILATION_CACHE_DIR``, else ``~/.cache/pusupu_jax/jax``.  Returns the cache directory.

    ``synchronous_cpu``: computations on the CPU run on the calling thread (no asynchronous dispatch), for the
    bridge's and the simulated robot's cycle thread (:func:`pusupu_jax.hw_bridge.compiled.cpu`).
    """
    import jax

    path = Path(
        cache_dir
        or os.environ.get("PUSUPU_JAX_CACHE")
        or os.environ.get("JAX_COMPILATION_CACHE_DIR")
        or Path.home() / ".cache" / "pusupu_jax" / "jax"
    )
    path.mkdir(parents=True, exist_ok=True)
    # jax leaves Config.update unannotated
    jax.config.update("jax_enable_x64", x64)  # type: ignore[no-untyped-call]
    jax.config.update("jax_compilation_cache_dir", str(path))  # type: ignore[no-untyped-call]
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # type: ignore[no-untyped-call]
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # type: ignore[no-untyped-call]
    if synchronous_cpu:
        jax.config.update("jax_cpu_enable_async_dispatch", False)  # type: ignore[no-untyped-call]
    return path


def require_x64(what: str) -> None:
    """RuntimeError unless JAX computes in float64 (:func:`setup_jax` turns it on): ``what`` needs it."""
    import jax

    if not jax.config.jax_enable_x64:  # type: ignore[attr-defined]  # JAX defines its flags at run time
        raise RuntimeError(f"{what} compute in float64: call pusupu_jax.runtime.setup_jax() first")
