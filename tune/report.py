"""What one tuning job reports: typed records of its ``report.json`` (``pusupu tune``'s run, and each job of
``pusupu batch``), and of a batch summary's row.

The records are what Python code passes around and reads by attribute; ``to_json()`` gives the file's content
(JSON types only, keys as in ``docs/tuning.md``) and ``from_json()`` reads it back.  A scenario's metrics are a
:class:`~pusupu_jax.metrics.MachineMetrics`, written with the highest branch force peak.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any, ClassVar

import numpy as np

from pusupu_jax.metrics import MachineMetrics, Metric

from .state import Evaluation

ScenarioMetrics = dict[str, MachineMetrics]  # scenario -> its metrics
Gains = dict[str, Any]  # tuned field -> value (a float or six per-axis floats)


class JobStatus(enum.StrEnum):
    """How a job ended: gains exported, tuned but refused by a check, or no start gave a finite result."""

    OK = "ok"
    NOT_EXPORTED = "not exported"
    FAILED = "failed"


def metrics_json(runs: ScenarioMetrics) -> dict[str, Any]:
    """A report's metrics of each scenario as plain data, with the highest branch force peak."""
    return {name: m.to_json(highest_force=True) for name, m in runs.items()}


def metrics_of(d: dict[str, Any]) -> ScenarioMetrics:
    """:func:`metrics_json`'s records."""
    return {name: MachineMetrics.from_json(m) for name, m in d.items()}


@dataclasses.dataclass(frozen=True)
class GainFileRef:
    """The gain file a report describes (``path`` and ``sha256``), or why none was written (``not_written``) and which
    earlier ``gains.yaml`` was left as it was (``left_as_it_was``: its path and sha256, or None)."""

    path: str | None
    sha256: str | None = None
    not_written: str | None = None
    left_as_it_was: dict[str, str] | None = None

    def to_json(self) -> dict[str, Any]:
        if self.not_written is None:
            return {"path": self.path, "sha256": self.sha256}
        return {"path": None, "not_written": self.not_written, "left_as_it_was": self.left_as_it_was}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> GainFileRef:
        return cls(d.get("path"), d.get("sha256"), d.get("not_written"), d.get("left_as_it_was"))


@dataclasses.dataclass(frozen=True)
class Export:
    """What became of the tuned gains: their margins, the files written, the gain file described, the check that
    refused them (``error``; None when exported), and where ROS's PID with the exported gains keeps less than the
    floors (``ros_warning``, :func:`pusupu_jax.ros2.short_of_floors`; None where it keeps them or nothing was
    exported)."""

    margins_after: dict[str, Any]
    exported: list[str]
    gains_file: GainFileRef
    error: str | None = None
    ros_warning: str | None = None

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"margins_after": self.margins_after, "exported": self.exported}
        if self.error is not None:
            d["export_error"] = self.error
        if self.ros_warning is not None:
            d["ros_warning"] = self.ros_warning
        return d | {"gains_file": self.gains_file.to_json()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Export:
        return cls(
            d["margins_after"],
            list(d["exported"]),
            GainFileRef.from_json(d["gains_file"]),
            d.get("export_error"),
            d.get("ros_warning"),
        )


@dataclasses.dataclass(frozen=True)
class TuneReport:
    """``pusupu tune``'s report (:func:`pusupu_jax.tune.job.run_job`), shown as the table the command prints
    (:func:`table`) rather than the whole history.  Wall times in seconds."""

    config: dict[str, Any]
    config_hash: str
    machine: dict[str, Any]
    start_gains: dict[str, Any]
    tuned_fields: list[str]
    start: Gains
    result: Gains
    objective_before: float
    objective_after: float
    history: list[Evaluation]
    before: ScenarioMetrics
    after: ScenarioMetrics
    baselines: dict[str, ScenarioMetrics]
    margins_before: dict[str, Any]
    optimise_wall_s: float
    export: Export
    plots: list[str]
    wall_s: float

    @property
    def iterations(self) -> int:
        """Evaluations of the objective, over every start."""
        return len(self.history)

    def to_json(self, history: bool = True) -> dict[str, Any]:
        """``report.json``'s content (without the history when ``history`` is False)."""
        d: dict[str, Any] = {
            "config": self.config,
            "config_hash": self.config_hash,
            "machine": self.machine,
            "start_gains": self.start_gains,
            "tuned_fields": self.tuned_fields,
            "start": self.start,
            "result": self.result,
            "objective_before": self.objective_before,
            "objective_after": self.objective_after,
            "iterations": self.iterations,
            "history": [h.to_json() for h in self.history],
            "before": metrics_json(self.before),
            "after": metrics_json(self.after),
            "baselines": {mode: metrics_json(runs) for mode, runs in self.baselines.items()},
            "margins_before": self.margins_before,
            "optimise_wall_s": self.optimise_wall_s,
        }
        if not history:
            del d["history"]
        return d | self.export.to_json() | {"plots": self.plots, "wall_s": self.wall_s}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> TuneReport:
        """The record of a ``report.json`` written by :meth:`to_json`."""
        return cls(
            config=d["config"],
            config_hash=d["config_hash"],
            machine=d["machine"],
            start_gains=d["start_gains"],
            tuned_fields=list(d["tuned_fields"]),
            start=d["start"],
            result=d["result"],
            objective_before=d["objective_before"],
            objective_after=d["objective_after"],
            history=[Evaluation.from_json(h) for h in d["history"]],
            before=metrics_of(d["before"]),
            after=metrics_of(d["after"]),
            baselines={mode: metrics_of(runs) for mode, runs in d["baselines"].items()},
            margins_before=d["margins_before"],
            optimise_wall_s=d["optimise_wall_s"],
            export=Export.from_json(d),
            plots=list(d["plots"]),
            wall_s=d["wall_s"],
        )

    def __repr__(self) -> str:
        return "TuneReport\n" + table(self)

    def _repr_markdown_(self) -> str:
        return f"```\n{self!r}\n```"


TABLE_METRICS = (
    Metric.RMS_TRACKING_ERROR_MM,
    Metric.MAX_TRACKING_ERROR_MM,
    Metric.SYNC_ERROR_RHO,
    Metric.HIGHEST_BRANCH_FORCE_PEAK_N,
)


def table(report: TuneReport) -> str:
    """The before/after table printed at the end of a run, with the baselines beside."""
    modes = list(report.baselines)
    lines = [
        f"{'scenario':<14} {'metric':<28} {'before':>10} {'after':>10} {'change':>8}"
        + "".join(f" {m:>10}" for m in modes)
        + (f" {'vs best':>8}" if modes else "")
    ]
    for name in report.before:
        b, a = report.before[name], report.after[name]
        for key in TABLE_METRICS:
            vb, va = b.value(key), a.value(key)
            change = (va / vb - 1) * 100 if vb else float("nan")
            base = [report.baselines[m][name].value(key) for m in modes]
            versus = f" {(va / min(base) - 1) * 100:>7.1f}%" if base and min(base) else ""
            lines.append(
                f"{name:<14} {key:<28} {vb:>10.4g} {va:>10.4g} {change:>7.1f}%"
                + "".join(f" {v:>10.4g}" for v in base)
                + versus
            )
    lines.append(
        f"objective {report.objective_before:.4f} -> {report.objective_after:.4f} in "
        f"{report.iterations} evaluations, {report.wall_s:.0f} s"
    )
    for field in report.tuned_fields:
        start, result = np.ravel(report.start[field]), np.ravel(report.result[field])
        lines.append(f"  {field:<8} {start[0]:.6g} -> {result[0]:.6g}" + (" (axis 1)" if len(result) > 1 else ""))
    if report.export.error is not None:
        lines.append(f"NOT EXPORTED: {report.export.error}")
    if report.export.ros_warning is not None:
        lines.append(f"warning: {report.export.ros_warning}")
    return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class SummaryRow:
    """One job's row of a batch's summary (``summary.csv``, ``.md``, ``.json``): means over its scenarios [mm, N],
    and the first value of each tuned field.  A job the job file could not give has no figures (None: left out of
    the JSON, empty in the CSV)."""

    job: str
    status: JobStatus
    scenarios: int
    objective_before: float | None
    objective_after: float | None
    rms_before_mm: float | None
    rms_after_mm: float | None
    max_after_mm: float | None
    force_peak_after_n: float | None
    error: str
    gains: dict[str, float] = dataclasses.field(default_factory=dict)

    COLUMNS: ClassVar[tuple[str, ...]] = (
        "job",
        "status",
        "scenarios",
        "objective_before",
        "objective_after",
        "rms_before_mm",
        "rms_after_mm",
        "max_after_mm",
        "force_peak_after_n",
        "error",
    )

    def to_json(self) -> dict[str, Any]:
        """The row as plain data (what a Ray task returns, and ``summary.json`` holds): the columns, then the gains."""
        plain = {c: str(self.status) if c == "status" else getattr(self, c) for c in self.COLUMNS}
        return {c: v for c, v in plain.items() if v is not None} | self.gains

    @classmethod
    def unread(cls, job: str, error: str) -> SummaryRow:
        """The row of a job that the job file could not give (``error``): no scenario, no figures."""
        return cls(job, JobStatus.FAILED, 0, None, None, None, None, None, None, error)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> SummaryRow:
        return cls(
            **{c: JobStatus(d[c]) if c == "status" else d.get(c) for c in cls.COLUMNS},
            gains={k: v for k, v in d.items() if k not in cls.COLUMNS},
        )


@dataclasses.dataclass(frozen=True)
class JobReport:
    """One batch job's report (``jobs/<job>/report.json``): its settings and scenarios, and, unless every start
    failed, the tuned gains, their metrics and their export."""

    job: str
    job_digest: str
    scenarios: list[dict[str, Any]]
    machine: dict[str, Any]
    start_gains: dict[str, Any]
    config: dict[str, Any]
    tuned_fields: list[str]
    failed_starts: dict[str, str]
    history: list[Evaluation]
    objective_before: float
    before: ScenarioMetrics
    status: JobStatus
    error: str
    objective_after: float = float("nan")
    after: ScenarioMetrics | None = None
    start: Gains | None = None
    result: Gains | None = None
    export: Export | None = None
    plots: list[str] | None = None

    def row(self) -> SummaryRow:
        def mean(runs: ScenarioMetrics | None, metric: Metric) -> float:
            return float(np.mean([r.value(metric) for r in runs.values()])) if runs else float("nan")

        return SummaryRow(
            job=self.job,
            status=self.status,
            scenarios=len(self.scenarios),
            objective_before=self.objective_before,
            objective_after=self.objective_after,
            rms_before_mm=mean(self.before, Metric.RMS_TRACKING_ERROR_MM),
            rms_after_mm=mean(self.after, Metric.RMS_TRACKING_ERROR_MM),
            max_after_mm=mean(self.after, Metric.MAX_TRACKING_ERROR_MM),
            force_peak_after_n=mean(self.after, Metric.HIGHEST_BRANCH_FORCE_PEAK_N),
            error=self.error,
            gains={f: float(np.ravel(v)[0]) for f, v in (self.result or {}).items()},
        )

    def to_json(self) -> dict[str, Any]:
        """``report.json``'s content; its ``row`` is the job's summary row."""
        d: dict[str, Any] = {
            "job": self.job,
            "job_digest": self.job_digest,
            "scenarios": self.scenarios,
            "machine": self.machine,
            "start_gains": self.start_gains,
            "config": self.config,
            "tuned_fields": self.tuned_fields,
            "failed_starts": self.failed_starts,
            "history": [h.to_json() for h in self.history],
            "objective_before": self.objective_before,
            "before": metrics_json(self.before),
        }
        if self.status is not JobStatus.FAILED:
            d |= {
                "objective_after": self.objective_after,
                "after": None if self.after is None else metrics_json(self.after),
                "start": self.start,
                "result": self.result,
            }
        if self.export is not None:
            d |= self.export.to_json()
        d |= {"status": str(self.status), "error": self.error}
        if self.plots is not None:
            d["plots"] = self.plots
        return d | {"row": self.row().to_json()}
