"""Shards of a batch as Ray tasks (``pusupu batch --ray [--address ADDR]``; the ``cluster`` extra installs Ray).

Each shard is one task running the shard function it is given (``pusupu batch`` gives
:func:`pusupu_jax.tune.batchjob.run_shard`, so this module imports no batch code): it asks for one GPU where the
cluster has GPUs, else ``cpus_per_task`` CPUs.  Ray schedules the tasks and retries one whose
worker dies (``max_retries``); the retry continues from the shard's checkpoint, so its result is
the uninterrupted one.  Without ``--address`` a local Ray instance starts with ``workers`` CPUs
(default: every core); with it, the batch joins that cluster, whose nodes must all see ``DIR``
(a shared file system), since the tasks write the checkpoints and the job outputs there.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time

from pusupu_jax import runtime
from pusupu_jax.params import ParameterError

MAX_RETRIES = 3


def run_tasks(
    run_shard,
    tasks: list[dict],
    out,
    *,
    plots: bool = True,
    address: str | None = None,
    workers: int | None = None,
    cpus_per_task: int = 1,
    stream=sys.stderr,
) -> list[list[dict]]:
    """Every task's result (``run_shard(task, out, plots)``: its summary rows), in task order; progress over shards on
    ``stream``."""
    try:
        import ray
    except ImportError:
        raise ParameterError('--ray: Ray is not installed; pip install -e ".[cluster]"') from None
    with contextlib.redirect_stdout(stream):  # Ray's own messages (a worker died...) stay off the summary's stdout
        return _run(ray, run_shard, tasks, out, plots, address, workers, cpus_per_task, stream)


def _run(ray, run_shard, tasks, out, plots, address, workers, cpus_per_task, stream):
    env = {
        k: v
        for k, v in os.environ.items()
        if k in ("PUSUPU_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR", "XLA_FLAGS", "JAX_PLATFORMS")
    }
    env["MPLBACKEND"] = "Agg"  # the workers' figures are files (importing the packages leaves the backend alone)
    env["XLA_FLAGS"] = runtime.xla_flags_for(cpus_per_task)  # a task computes on the CPUs it asks for, one device each
    if address is None:
        ray.init(
            num_cpus=workers or os.cpu_count(),
            include_dashboard=False,
            runtime_env={"env_vars": env},
            log_to_driver=True,
        )
    else:
        ray.init(address=address, runtime_env={"env_vars": env}, log_to_driver=True)
    try:
        gpus = 1 if ray.cluster_resources().get("GPU", 0) >= 1 else 0
        remote = ray.remote(num_cpus=cpus_per_task, num_gpus=gpus, max_retries=MAX_RETRIES)(run_shard)
        refs = [remote.remote(task, str(out), plots) for task in tasks]
        index = {ref: k for k, ref in enumerate(refs)}
        results, pending, t0 = [None] * len(refs), list(refs), time.perf_counter()
        print(
            f"batch: {len(refs)} Ray task(s) on {ray.cluster_resources().get('CPU', 0):g} CPU(s), "
            f"{gpus and ray.cluster_resources().get('GPU', 0):g} GPU(s); each task "
            + ("one GPU" if gpus else f"{cpus_per_task} CPU(s)"),
            file=stream,
            flush=True,
        )
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            results[index[ready[0]]] = ray.get(ready[0])
            print(
                f"batch: {len(refs) - len(pending)}/{len(refs)} shard(s) done, {time.perf_counter() - t0:.0f} s",
                file=stream,
                flush=True,
            )
        return results
    finally:
        ray.shutdown()
