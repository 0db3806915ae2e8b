"""Batch job files (``pusupu batch JOB.yaml``): reading, checking, and splitting into jobs and compiled groups.

A job file (JSON Schema: ``tune/schemas/pusupu-batch.schema.json``; ``docs/batch.md``)::

    format: pusupu-batch-1
    problems: independent      # independent: one gain set per scenario | robust: one gain set for all of them
    name: robust               # the robust job's name (robust only)
    shard_size: 64             # at most this many jobs (independent) or starts (robust) per task; null: one task
    plots: true                # per-job plots (objective, paths, forces)
    machine: my_robot.yaml     # the machine file every job runs on (docs/machine.md; relative: from the job file's
                               #   folder); default the built-in machine.  Its start gains as pusupu tune's.
    tune:                      # every pusupu tune key but the scenario ones (trajectories, kin_error_seeds,
      iterations: 10           #   payloads, draws, path_s, baselines): groups, weights, the optimiser, starts, ...
      starts: 2                #   mode, windows and window_s are the scenarios' defaults
    scenarios:
      - name: arc-seed1        # default: trajectory/seedN/Pkg (a path file: its stem)
        trajectory: arc        # arc | p2p | circle | tilt | excite | a path file (.yaml, .yml, .csv; docs/paths.md),
                               # a relative file name taken from the job file's folder
        machine: other.yaml    # this scenario's machine file, in place of the file's (relative: as above)
        mode: hybrid           # hybrid | imc | pid | pid_ff (default: tune.mode)
        payload: 0.0           # kg added to the machine's payload, at its centre of mass
        kin_error_seed: 1      # seeded 0.5 mm errors of the simulated machine (null: none)
        geometry: {rod_lengths: [0.9, 0.9, 0.9, 0.9, 0.9, 0.9]}   # overrides of the machine's geometry fields
        path_s: 2.0            # s: the first path_s seconds of the path (null: all of it)
        windows: 2             # training windows spread over the path (default: tune.windows)
        window_s: 0.3          # s, each window's length (default: tune.window_s)

A scenario that is malformed, names an unknown key or whose path the machine cannot follow (its
workspace, its motors' speed and torque: :func:`pusupu_jax.paths.check_path`), or a job of more work than
:func:`pusupu_jax.tune.run.check_work` allows, fails its own job (:class:`Job` with ``error``); the other jobs run.
A file that is not such a mapping fails as a whole.  A robust problem takes one machine for all its
scenarios (one set of drives, one start).
Jobs on one machine whose settings compile to the same shapes (mode, windows, window_s) form one group: one
compiled gradient serves all of them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pusupu_jax import inputs, machine_file, paths
from pusupu_jax.machine import machine_rates
from pusupu_jax.machine_file import Machine
from pusupu_jax.params import ParameterError, ServoParams
from pusupu_jax.plant.geometry import Geometry, validate_geometry
from pusupu_jax.plant.model import ModelOptions

from .config import TuneConfig
from .run import ScenarioSpec, check_work

FORMAT = "pusupu-batch-1"
SCHEMA_FILE = Path(__file__).resolve().parent / "schemas" / "pusupu-batch.schema.json"
FILE_KEYS = ("format", "problems", "name", "shard_size", "plots", "machine", "tune", "scenarios")
SCENARIO_KEYS = (
    "name",
    "trajectory",
    "machine",
    "mode",
    "payload",
    "kin_error_seed",
    "geometry",
    "path_s",
    "windows",
    "window_s",
)
SCENARIO_TUNE_KEYS = ("mode", "windows", "window_s")  # per scenario, default from tune:
NOT_IN_TUNE = ("trajectories", "kin_error_seeds", "payloads", "draws", "path_s", "baselines")  # the scenarios say these
GEOMETRY_FIELDS = tuple(f.name for f in dataclasses.fields(Geometry))


class JobFileError(ParameterError):
    """A job file, or one scenario of it, is not as expected."""


@dataclass(frozen=True, eq=False)
class Job:
    """One tuning problem: its scenarios and settings, or the error that keeps it from running."""

    name: str
    config: TuneConfig | None
    specs: tuple  # ScenarioSpec
    error: str | None = None
    machine: Machine | None = None  # None: the built-in machine

    def group_key(self) -> tuple:
        """Jobs with equal keys run on one machine and compile to the same shapes (one group, one compiled
        gradient)."""
        c = self.config
        machine = None if self.machine is None else machine_file.digest(self.machine)
        return (c.mode, c.windows, c.window_s, len(self.specs), machine)

    def digest(self) -> str:
        """A hash of the job's settings and scenarios, and of their path files' contents (its report and its group's
        checkpoint carry it)."""
        files = [paths.source_digest(s.trajectory) for s in self.specs if paths.is_path_file(s.trajectory)]
        machine = [] if self.machine is None else [machine_file.digest(self.machine)]
        text = json.dumps(
            [self.config.digest(), [spec_dict(s) for s in self.specs]] + ([files] if files else []) + machine,
            sort_keys=True,
            default=str,
        )
        return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True, eq=False)
class JobFile:
    path: str
    problems: str
    shard_size: int | None
    plots: bool
    jobs: tuple  # Job
    machine: Machine


def job_name(name: object, where: str) -> str:
    """A job's name, which names its folder under the batch's ``jobs/``: letters, digits and ``- _ . /``, not
    starting with a dot; :class:`JobFileError` naming ``where`` otherwise."""
    if (
        not isinstance(name, str)
        or not name
        or name.startswith(".")
        or not all(c.isalnum() or c in "-_./" for c in name)
    ):
        raise JobFileError(f"{where}: expected letters, digits and - _ . / (not first: .), got {name!r}")
    return name


def spec_dict(spec: ScenarioSpec) -> dict:
    """A scenario as plain data (JSON), the inverse of :func:`spec_from_dict`."""
    geometry = (
        None if spec.geometry is None else {f: np.asarray(getattr(spec.geometry, f)).tolist() for f in GEOMETRY_FIELDS}
    )
    o = spec.options
    return {
        "name": spec.name,
        "trajectory": spec.trajectory,
        "payload": o.payload,
        "payload_com": list(o.payload_com),
        "payload_inertia": list(o.payload_inertia),
        "kin_error_seed": o.kin_error_seed,
        "geometry": geometry,
        "path_s": spec.path_s,
    }


def spec_from_dict(d: dict) -> ScenarioSpec:
    geometry = None if d["geometry"] is None else Geometry(**{k: np.asarray(v) for k, v in d["geometry"].items()})
    options = ModelOptions(
        kin_error_seed=d["kin_error_seed"],
        payload=float(d["payload"]),
        payload_com=tuple(d["payload_com"]),
        payload_inertia=tuple(d["payload_inertia"]),
    )
    return ScenarioSpec(d["name"], d["trajectory"], options, geometry, d["path_s"])


def _geometry(value, where: str, machine: Machine) -> Geometry:
    """The machine's geometry with the scenario's overrides ``value`` (None: none), checked."""
    if value is None:
        return machine.geometry
    inputs.check_keys(value, where, GEOMETRY_FIELDS, JobFileError, what="geometry field")
    base = machine.geometry
    changes = {}
    for k, v in value.items():
        changes[k] = inputs.array(v, f"{where}.{k}", np.shape(getattr(base, k)), JobFileError)
    geom = base.replace(**changes)
    try:
        validate_geometry(geom)
    except ParameterError as e:
        raise JobFileError(f"{where}: {e}") from None
    return geom


class _Machines:
    """The machine files a job file names, each read and checked once: ``(machine, the drives' limits)`` by name
    (relative to the job file's ``folder``; None: the file's own machine, ``default``, that of its ``machine:`` key
    ``source`` or the built-in one)."""

    def __init__(self, folder: Path, source, where: str):
        self.folder = folder
        self.read: dict[str | None, tuple[Machine, ServoParams]] = {}
        self.default = Machine.default() if source is None else self(source, where)[0]

    def __call__(self, source, where: str) -> tuple[Machine, ServoParams]:
        if source not in self.read:
            if source is None:
                machine = self.default
            elif not isinstance(source, str) or not source:
                raise JobFileError(f"{where}: expected the name of a machine file, got {inputs.shown(source)}")
            else:
                try:
                    machine = machine_file.load(self.folder / source)  # an absolute name stays as it is
                except ParameterError as e:
                    raise JobFileError(f"{where}: {e}") from None
            self.read[source] = (machine, start_limits(machine))
        return self.read[source]


def _scenario(
    entry, k: int, base: TuneConfig, folder: Path, machines: _Machines
) -> tuple[ScenarioSpec, TuneConfig, Machine]:
    """Scenario ``k``'s spec, its job's configuration and its machine (a path file named relative to ``folder``, the
    job file's; the path checked against the machine's drives); raises :class:`JobFileError` naming it."""
    where = f"scenarios[{k}]"
    inputs.check_keys(entry, where, SCENARIO_KEYS, JobFileError, required=("trajectory",))
    machine, limits = machines(entry.get("machine"), f"{where}.machine")
    trajectory = paths.resolve(paths.check_spec(entry["trajectory"], f"{where}.trajectory", JobFileError), folder)
    seed = entry.get("kin_error_seed")
    if seed is not None:
        seed = inputs.integer(seed, f"{where}.kin_error_seed", JobFileError, low=0)
    payload = inputs.number(entry.get("payload", 0.0), f"{where}.payload", JobFileError, low=0.0, high=1000.0)
    path_s = entry.get("path_s")
    if path_s is not None:
        path_s = inputs.number(path_s, f"{where}.path_s", JobFileError, low=0.0, low_open=True, high=3600.0)
    default_name = (
        paths.path_label(trajectory)
        + (f"/seed{seed}" if seed is not None else "")
        + (f"/{payload:g}kg" if payload else "")
    )
    name = job_name(entry.get("name", default_name), f"{where}.name")
    try:
        cfg = base.replace(**{key: entry[key] for key in SCENARIO_TUNE_KEYS if key in entry})
    except ParameterError as e:
        raise JobFileError(f"{where}: {str(e).replace('tune config ', '')}") from None
    options = machine.options(ModelOptions(kin_error_seed=seed))
    options = dataclasses.replace(options, payload=options.payload + payload)
    spec = ScenarioSpec(
        name, trajectory, options, _geometry(entry.get("geometry"), f"{where}.geometry", machine), path_s
    )
    check_scenario(spec, cfg, where, limits)
    return spec, cfg, machine


def check_scenario(spec: ScenarioSpec, cfg: TuneConfig, where: str, limits: ServoParams) -> None:
    """Before any compile: the machine can follow the path (:func:`pusupu_jax.paths.check_path` with the drives and
    current limits of ``limits``, the batch's start) and it holds ``cfg.windows`` windows of ``cfg.window_s``."""
    rates = machine_rates()
    try:
        path = spec.path(rates)
        paths.check_path(
            path,
            limits,
            rates.dt_position,
            spec.geom(),
            spec.options,
            where=f"the {paths.path_label(spec.trajectory)} path",
        )
    except ParameterError as e:
        raise JobFileError(f"{where} ({spec.name}): {e}{spec.cut_note(limits, rates)}") from None
    every = -(-len(path) // cfg.windows)
    if round(cfg.window_s / rates.dt_position) > every:
        raise JobFileError(
            f"{where} ({spec.name}): window_s expected at most a {cfg.windows}th of the path "
            f"({every * rates.dt_position:g} s), got {cfg.window_s:g}"
        )


def bounded(job: Job) -> Job:
    """``job``, or ``job`` failed when the tuning work it implies is beyond the limits
    (:func:`pusupu_jax.tune.run.check_work`)."""
    if job.error is None:
        try:
            check_work(job.config, list(job.specs), where="its tuning work")
        except ParameterError as e:
            return Job(job.name, None, (), str(e))
    return job


def read(path) -> JobFile:
    """The job file at ``path``: its jobs, each ready to run or holding the error that keeps it from running.

    Raises :class:`JobFileError` (one line) when the file as a whole is unusable.
    """
    path = Path(path)
    data = inputs.read_yaml(path, "job file", JobFileError)
    where = str(path)
    inputs.check_keys({} if data is None else data, where, FILE_KEYS, JobFileError, required=("scenarios",))
    if data.get("format", FORMAT) != FORMAT:
        raise JobFileError(f"{where}: format: expected {FORMAT!r}, got {data['format']!r}")
    problems = inputs.choice(
        data.get("problems", "independent"), f"{where}: problems", ("independent", "robust"), JobFileError
    )
    shard = data.get("shard_size")
    if shard is not None:
        shard = inputs.integer(shard, f"{where}: shard_size", JobFileError, low=1)
    plots = data.get("plots", True)
    if not isinstance(plots, bool):
        raise JobFileError(f"{where}: plots: expected true or false, got {plots!r}")
    tune = inputs.check_keys(
        data.get("tune") or {},
        f"{where}: tune",
        [f.name for f in dataclasses.fields(TuneConfig) if f.name not in NOT_IN_TUNE],
        JobFileError,
    )
    try:
        base = TuneConfig().replace(baselines=(), **tune)
    except ParameterError as e:
        raise JobFileError(f"{where}: {e}") from None
    machines = _Machines(path.parent, data.get("machine"), f"{where}: machine")
    scenarios = data["scenarios"]
    if not isinstance(scenarios, list) or not scenarios:
        raise JobFileError(f"{where}: scenarios: expected a non-empty list of scenarios, got {scenarios!r}")
    parsed: list = []
    for k, entry in enumerate(scenarios):
        try:
            parsed.append(_scenario(entry, k, base, path.parent, machines))
        except ParameterError as e:
            name = entry.get("name") if isinstance(entry, dict) and isinstance(entry.get("name"), str) else None
            parsed.append((name or f"scenario{k}", str(e)))

    def on(machine: Machine) -> Machine | None:
        return None if machine_file.is_builtin(machine) else machine

    if problems == "independent":
        jobs = [
            Job(p[0].name, p[1], (p[0],), machine=on(p[2]))
            if isinstance(p[0], ScenarioSpec)
            else Job(p[0], None, (), p[1])
            for p in parsed
        ]
    else:
        name = job_name(data.get("name", "robust"), f"{where}: name")
        ok = [p for p in parsed if isinstance(p[0], ScenarioSpec)]
        errors = [p[1] for p in parsed if not isinstance(p[0], ScenarioSpec)]
        configs = {(c.mode, c.windows, c.window_s) for _, c, _ in ok}
        if not errors and len(configs) > 1:
            errors = [f"robust problems need one mode, windows and window_s for every scenario; got {sorted(configs)}"]
        on_machines = {machine_file.digest(m): m.name for _, _, m in ok}
        if not errors and len(on_machines) > 1:
            errors = [
                "robust problems need one machine for every scenario (one set of drives, one start); got "
                + ", ".join(sorted(f"{n!r} ({d[:12]})" for d, n in on_machines.items()))
            ]
        jobs = [
            Job(name, None, (), errors[0])
            if errors
            else Job(name, parsed[0][1], tuple(s for s, _, _ in parsed), machine=on(parsed[0][2]))
        ]
    jobs = [bounded(job) for job in jobs]
    names = [j.name for j in jobs]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise JobFileError(f"{where}: scenarios: expected distinct names, got {dup!r} twice")
    return JobFile(str(path), problems, shard, plots, tuple(jobs), machines.default)


def start_limits(machine: Machine) -> ServoParams:
    """The drives and current limits a batch on ``machine`` starts from, for the path checks: Table 1's on the built-in
    machine, else the limits the start gains derive (the machine's ratings; no identification needed for them)."""
    if machine_file.is_builtin(machine):
        return machine.servo(ServoParams.table1())
    from pusupu_jax.start_gains import derive

    return derive(machine, identify=False)[0]


def groups(jobs) -> dict:
    """``{group key: [jobs]}`` of the runnable jobs, in file order."""
    out = {}
    for job in jobs:
        if job.error is None:
            out.setdefault(job.group_key(), []).append(job)
    return out
