"""Timing shared by the benchmark scripts (imported from beside them)."""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time


def processor() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` says."""
    import platform
    from pathlib import Path

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def parse_config(item: str, platforms: tuple[str, ...] = ("cpu", "gpu")) -> tuple[str, str, str | None]:
    """``LABEL=PLATFORM[@CPUS]`` (PLATFORM one of ``platforms``; CPUS as ``taskset -c`` takes them) as ``(label,
    platform, cpus or None)``; anything else ends the benchmark in one line."""
    label, _, spec = item.partition("=")
    name, _, cpus = spec.partition("@")
    if name not in platforms or not label:
        raise SystemExit(f"expected LABEL=PLATFORM[@CPUS] with PLATFORM one of {', '.join(platforms)}, got {item!r}")
    return label, name, cpus or None


def pinned(cmd: list[str], platform_name: str, cpus: str | None, what: str, cwd=None, **env: str):
    """Run ``cmd`` (captured) on the platform and CPUs asked, with ``env`` added to this process's environment but
    for its ``PUSUPU_JAX_CACHE`` and ``JAX_PLATFORMS``; a failure ends the benchmark in one line naming ``what`` ran
    and its last line of stderr."""
    full = {k: v for k, v in os.environ.items() if k not in ("PUSUPU_JAX_CACHE", "JAX_PLATFORMS")} | env
    if platform_name == "cpu":
        full["JAX_PLATFORMS"] = "cpu"
    if cpus:
        cmd = ["taskset", "-c", cpus] + cmd
    done = subprocess.run(cmd, env=full, cwd=cwd, capture_output=True, text=True, timeout=3600)
    if done.returncode:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"{what} ({platform_name} {cpus or ''}) failed: {last}")
    return done


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
    :func:`pusupu_jax.hw_bridge.runner.percentiles` dict, ``<stem>_us``) over ``runs``, leaving out runs where it is
    None."""
    stem = field.removesuffix("_us")
    return {f"{stem}_{p}_us": spread([r[field][p] for r in runs if r[field] is not None]) for p in points}


def emit(result: dict, out: str | None, indent: int = 1) -> None:
    """Print ``result`` as JSON, and write it to ``out`` too when given (atomically, with the umask's mode)."""
    import json

    from pusupu_jax.files import write_atomic

    text = json.dumps(result, indent=indent)
    print(text)
    if out:
        write_atomic(out, text + "\n")


def steal_ms_since(before) -> list | None:
    """Per CPU, the hypervisor's steal time [ms] since ``before`` (a :func:`pusupu_jax.hw_bridge.runner.steal_seconds`
    reading),
    or None where either reading is missing."""
    from pusupu_jax.hw_bridge.runner import steal_seconds

    now = steal_seconds()
    return None if before is None or now is None else (1e3 * (now - before)).tolist()


PROBE = r"""
import json, signal, sys, time
from pusupu_jax.hw_bridge.runner import realtime_setup
signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
rt = realtime_setup(priority=int(sys.argv[2]), cpu=int(sys.argv[1]))
print("ready", flush=True)
gaps, last = [], time.monotonic()
try:
    while True:
        time.sleep(0.0005)
        now = time.monotonic()
        if now - last > float(sys.argv[3]):
            gaps.append((last, now - last))
        last = now
finally:
    rt.restore()
    print(json.dumps({"realtime": rt.settings, "gaps": gaps}), flush=True)
"""


class PauseProbe:
    """The machine's own pauses while it runs: one process on each CPU, with the bridge's real-time settings at
    ``priority`` (default 90, above the bridge's 80 and the simulated robot's 70), sleeps 0.5 ms at a time and records
    every return more than ``gap`` [s] after the one before, with its monotonic time, until :meth:`stop`.

    Above every other real-time thread and using a few per cent of its CPU, a probe that does not return for ``gap``
    means the guest kernel did not run that CPU's highest-priority thread; gaps that overlap on every CPU are the
    whole machine stopping at once (a hypervisor pause, counted as steal or not).  Each wake-up takes a few us from
    whatever runs on that CPU, so runs with the probe are for diagnosis, not for latency figures."""

    def __init__(self, priority: int = 90, gap: float = 2e-3):
        from pusupu_jax.hw_bridge.runner import steal_seconds

        self.gap = gap
        self.cpus = sorted(os.sched_getaffinity(0))
        self.steal = steal_seconds()
        self.procs = [
            subprocess.Popen(
                [sys.executable, "-c", PROBE, str(c), str(priority), str(gap)], stdout=subprocess.PIPE, text=True
            )
            for c in self.cpus
        ]
        for p in self.procs:
            assert p.stdout.readline().strip() == "ready"
        self.started = time.monotonic()

    def stop(self) -> dict:
        """Each CPU's gaps, and the intervals in which all CPUs were stopped (``spans``: monotonic start [s], length
        [ms], the first 50)."""
        for p in self.procs:
            p.terminate()
        found = [json.loads(p.communicate(timeout=60)[0]) for p in self.procs]
        stolen = steal_ms_since(self.steal)
        spans = [[(a, a + d) for a, d in f["gaps"]] for f in found]
        together = spans[0]
        for other in spans[1:]:  # the intersection of every CPU's gaps
            together = [(max(a, c), min(b, d)) for a, b in together for c, d in other if max(a, c) < min(b, d)]
        lengths = [1e3 * (b - a) for a, b in together]
        return {
            "seconds": time.monotonic() - self.started,
            "threshold_ms": 1e3 * self.gap,
            "realtime": [f["realtime"] for f in found],
            "steal_ms_per_cpu": stolen,
            "per_cpu": [
                {"cpu": c, "gaps": len(f["gaps"]), "max_ms": 1e3 * max((d for _, d in f["gaps"]), default=0.0)}
                for c, f in zip(self.cpus, found)
            ],
            "all_cpus_stopped": {
                "count": len(together),
                "max_ms": max(lengths, default=0.0),
                "total_ms": sum(lengths),
                "spans": [(a, 1e3 * (b - a)) for a, b in sorted(together)][:50],
            },
        }


# The first lines of a benchmark's child interpreter that measures a source tree (its folder is the child's last
# argument and first on PYTHONPATH): the tree's tune/ is mounted as pusupu_jax.tune, since an installed copy of the
# package (an editable install of another tree) would otherwise supply it.
MOUNT_TREE = r"""
import importlib.util, os, sys
import pusupu_jax
_tune = os.path.join(sys.argv[-1], "tune")
_spec = importlib.util.spec_from_file_location("pusupu_jax.tune", os.path.join(_tune, "__init__.py"),
                                               submodule_search_locations=[_tune])
sys.modules["pusupu_jax.tune"] = _module = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_module)
"""
