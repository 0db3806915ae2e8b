"""Timing shared by the benchmark scripts (imported from beside them)."""

from __future__ import annotations

import statistics
import time


def median_time(fn, repeats: int) -> float:
    """Median wall time [s] of ``repeats`` calls of ``fn()``, each awaited, after one warm-up call (the compile)."""
    import jax

    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def spread(values) -> dict | None:
    """min, median and max of ``values`` over a benchmark's runs, or None when there are none."""
    if not len(values):
        return None
    return {"min": float(min(values)), "median": float(statistics.median(values)), "max": float(max(values))}


def percentile_spreads(runs, field: str, points) -> dict:
    """``{'<stem>_<point>_us': spread}`` of each percentile ``point`` of ``run[field]`` (a
    :func:`hw_bridge.runner.percentiles` dict, ``<stem>_us``) over ``runs``, leaving out runs where it is None."""
    stem = field.removesuffix("_us")
    return {f"{stem}_{p}_us": spread([r[field][p] for r in runs if r[field] is not None]) for p in points}


def emit(result: dict, out: str | None, indent: int = 1) -> None:
    """Print ``result`` as JSON, and write it to ``out`` too when given (atomically, with the umask's mode)."""
    import json

    from pusupu_jax.config import write_atomic

    text = json.dumps(result, indent=indent)
    print(text)
    if out:
        write_atomic(out, text + "\n")
