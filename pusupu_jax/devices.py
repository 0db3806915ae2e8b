"""Which device computes a command's work (``--device auto|cpu|gpu``), and how a batch of independent rows (the
training windows of one tuning problem) is spread over the devices (host-side).

A rollout of the machine is a scan of small steps: on a GPU each step is a few dozen kernel launches whatever the
batch width; on a CPU core its cost grows with the width, from a fixed cost that a few rows already pay.  So a GPU
pays only for wide batches, and ``auto`` chooses it only when the work's width (the rows one gradient computes:
members x scenarios x windows) reaches :data:`GPU_CROSSOVER_ROWS` (docs/benchmarks.md); otherwise the CPU.

On the CPU, :func:`pusupu_jax.runtime.apply_xla_workaround` makes one XLA host device per core the process may run
on (``--xla_force_host_platform_device_count``), and :func:`row_mesh` lays a batch's rows over them, so that the
independent windows (and the paths of the forward pass) run on every core together instead of on one.
"""

from __future__ import annotations

import contextlib
import enum
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TextIO

from . import runtime
from .params import ParameterError

if TYPE_CHECKING:
    import jax
    from jax.sharding import Mesh

# The rows of one batch from which ``auto`` takes the GPU.  Measured on a 16-core Xeon host with one H200 (jax 0.11.2,
# benchmarks/bench_batch.py --path 3 --window 0.5 --windows 6, the default tune's windows; docs/benchmarks.md): 96 rows
# ran 4.23 s an iteration on the GPU against 9.17 s on all 16 cores (16 XLA host devices); 12 rows ran 3.86 s on the
# GPU, about what two cores of the 2-core CPU take for the default tune's 12 (4.1 s a gradient iteration), and on the
# same host's H100 the default tune itself (12 rows) ran 20-30 s an iteration against 4.7 s on two cores.  The GPU is
# taken from the smallest width at which it was measured faster than the host's whole CPU; below it, the CPU.
GPU_CROSSOVER_ROWS = 96


class DeviceChoice(enum.StrEnum):
    """``--device``: ``auto`` (the measured crossover), ``cpu`` or ``gpu``."""

    AUTO = "auto"
    CPU = "cpu"
    GPU = "gpu"


def gpu_available() -> bool:
    """Whether JAX has a GPU backend (initialises JAX's backends)."""
    import jax

    try:
        return bool(jax.devices("gpu"))
    except RuntimeError:
        return False


_chosen: str | None = None  # the platform select() chose for this process (None: JAX's default backend's)
_why: str | None = None  # and why (choose())


def select(requested: DeviceChoice | str, rows: int, what: str = "") -> tuple[str, str]:
    """``(platform, why)`` for work whose widest batch has ``rows`` independent rows (``what``: those rows in words):
    ``cpu`` or ``gpu``, and a few words on why; the process computes there from now on (:func:`chosen_devices`).

    Best called before JAX's backends start (the first computation): a CPU choice then keeps the GPU's backend from
    starting, so that it takes no GPU memory.  :class:`ParameterError` when a GPU is asked for and none is found.
    """
    global _chosen
    import jax

    requested = DeviceChoice(requested)
    if requested is DeviceChoice.GPU:
        if not (runtime.gpu_plugin_installed() and gpu_available()):
            raise ParameterError("--device gpu: expected a GPU that JAX can use, found none (jax.devices('gpu'))")
        platform, why = "gpu", "asked for (--device gpu)"
    elif requested is DeviceChoice.CPU:
        platform, why = "cpu", "asked for (--device cpu)"
    elif not runtime.gpu_plugin_installed():
        platform, why = "cpu", "auto: no GPU plugin for JAX is installed"
    elif rows < GPU_CROSSOVER_ROWS:
        platform, why = (
            "cpu",
            f"auto: {what or rows} in one batch, below the {GPU_CROSSOVER_ROWS} rows from which a GPU was faster",
        )
    elif not gpu_available():
        platform, why = "cpu", "auto: no GPU found"
    else:
        platform, why = (
            "gpu",
            f"auto: {what or rows} in one batch, from the {GPU_CROSSOVER_ROWS} rows at which a GPU was faster",
        )
    if platform == "cpu":
        # jax leaves Config.update unannotated
        jax.config.update("jax_platforms", "cpu")  # type: ignore[no-untyped-call]  # no GPU backend, if none has started yet
        jax.config.update("jax_default_device", jax.devices("cpu")[0])  # type: ignore[no-untyped-call]
    _chosen = platform
    return platform, why


def choose(requested: DeviceChoice | str, rows: int, what: str) -> str:
    """:func:`select`, kept for :func:`announce` (a command chooses before its checks and says so once they pass);
    returns the platform."""
    global _why
    platform, _why = select(requested, rows, what)
    return platform


def announce(stream: TextIO | None = None) -> None:
    """One line on ``stream`` (default stderr) before a command's work: ``computing on cpu (2 device(s) on 2 core(s)):
    auto: ...``, or on JAX's default backend when nothing was chosen (a notebook)."""
    import jax

    platform = _chosen or jax.default_backend()
    print(f"computing on {describe(platform)}: {_why or 'JAX default'}", file=stream or sys.stderr, flush=True)


def chosen_devices() -> list[jax.Device]:
    """The devices of the platform :func:`select` chose, else those of JAX's default backend."""
    import jax

    return list(jax.devices(_chosen))


def forward_pass_devices(rows: int) -> list[jax.Device]:
    """The devices a forward pass over ``rows`` whole paths (a tuning problem's scenarios) runs on: the chosen
    platform's (:func:`chosen_devices`), but where that is a GPU, the host CPU's while ``rows`` is at most their
    number (a path a core).  Such a pass is a scan of small steps, some 2 ms a position period on an H200 whatever its
    width, against about 1 ms a path on a core (docs/benchmarks.md)."""
    import jax

    chosen = chosen_devices()
    if chosen[0].platform == "cpu":
        return chosen
    host = list(jax.devices("cpu"))
    return host if rows <= len(host) else chosen


def set_up_device() -> contextlib.AbstractContextManager[Any]:
    """Where a tuning problem's set-up computes (its references, pose Jacobians and checks: small programs whose
    results go to the host): under ``with``, the host CPU's first device where the chosen platform is a GPU, as for
    the forward passes (:func:`forward_pass_devices`); else JAX's default, unchanged."""
    import jax

    host = forward_pass_devices(1)[0]
    return jax.default_device(host) if host.platform != chosen_devices()[0].platform else contextlib.nullcontext()


def describe(platform: str) -> str:
    """``cpu (N devices on N cores)`` or ``gpu (NAME)``, for a progress line."""
    import jax

    devices = jax.devices(platform)
    if platform == "cpu":
        return f"cpu ({len(devices)} device(s) on {runtime.cpu_count()} core(s))"
    return f"gpu ({devices[0].device_kind})"


def row_mesh(rows: int, devices: Sequence[jax.Device] | None = None) -> Mesh | None:
    """A one-axis mesh (axis ``rows``) over the largest number of ``devices`` (default :func:`chosen_devices`)
    that divides ``rows``, or None when that is one device."""
    import numpy as np
    from jax.sharding import Mesh

    devices = chosen_devices() if devices is None else devices
    n = max(d for d in range(1, len(devices) + 1) if rows % d == 0)
    return None if n == 1 else Mesh(np.array(list(devices)[:n]), ("rows",))


def spread_rows(tree: Any, mesh: Mesh | None) -> Any:
    """``tree`` with its leading axis laid over ``mesh``'s devices, inside a traced function (no-op without one)."""
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    if mesh is None:
        return tree
    # jax leaves with_sharding_constraint and PartitionSpec's constructor unannotated
    return jax.lax.with_sharding_constraint(tree, NamedSharding(mesh, PartitionSpec("rows")))  # type: ignore[no-untyped-call]
