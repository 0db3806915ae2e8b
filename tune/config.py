"""The tuning job's configuration: defaults embedded here, overridable from a YAML file.

Every key of :class:`TuneConfig` may appear in the file (unknown keys are errors)::

    mode: hybrid               # hybrid | imc | pid | pid_ff: the machine's control mode
    imc_form: full             # full | printed: the IMC prefilter C1 (docs/imc.md)
    groups: [imc, velocity, hybrid]   # what to tune: imc (lambda1, lambda2, T0), velocity (Kv, Tv),
                               # current (Ki, Ti), pid (Kp, Ki, Kd, Tf of the PID), feedforward (Kff_pid), hybrid
    shared: true               # one value for all six axes (false: one per axis)
    trajectories: [arc, p2p]   # paths: arc, p2p, circle, tilt, excite, or path files (.yaml, .yml, .csv;
                               # docs/paths.md), a relative file name taken from the configuration file's folder
    path_s: null               # s: use the first path_s seconds of each path (null: the whole paths)
    windows: 6                 # training windows per path, spread over it: window k starts at k/windows of it
    window_s: 0.5              # s, the length of each training window
    refresh_every: 5           # iterations between forward passes over the whole paths that renew the windows'
                               # start states
    kin_error_seeds: [null]    # robust tuning: scenarios with seeded kinematic errors
    payloads: [0.0]            # kg, scenarios with a payload on the platform
    draws: 0                   # robust tuning: each scenario also on this many machines drawn from the machine
                               # file's uncertainty section (pusupu identify writes it; docs/tuning.md)
    aggregate: mean            # mean | max over scenarios
    iterations: 25
    learning_rate: 0.1         # Adam on the log-parameters
    final_lr_fraction: 1.0     # cosine decay of the learning rate to this fraction (1: constant)
    clip_norm: 1.0             # gradient clipping (global norm)
    starts: 1                  # multi-start: extra starts are random log-perturbations (std start_spread)
    start_spread: 0.3
    seed: 0
    checkpoint_every: 5        # iterations; a multiple of refresh_every (a resumed run renews where it stopped)
    weights: {track_rms: 1.0, balance: 0.1}   # objective terms (pusupu_jax.objectives.TERMS), each
                                              # divided by its value at the start
    force_peak_limit: 1.0      # the smooth force peak may not exceed this times its start value
    pm_min: 45.0               # deg, every loop of every axis
    gm_min: 6.0                # dB
    sharpness_force: 1.0       # 1/N, smooth peak of the branch forces
    bounds: {lambda2: [0.01, 0.5]}   # per tuned field [lower, upper]; default start/10 .. start*10
    gradient: reverse          # reverse | forward: how the gradient is taken (pusupu_jax.gradients)
    remat: false               # true: reverse mode keeps each position period's carry only and runs it again
    baselines: [pid, pid_ff]   # modes run beside the start and the result on the whole paths, Table 1 gains
    ros_joints: [slide_1, slide_2, slide_3, slide_4, slide_5, slide_6]   # joint names of the ROS 2 export
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from pusupu_jax.cascade import control_mode
from pusupu_jax.files import read_yaml_mapping
from pusupu_jax.gradients import GRADIENT_MODES
from pusupu_jax.cascade import BASELINE_MODES, TUNE_MODES, Mode
from pusupu_jax.objectives import TERMS
from pusupu_jax import inputs, paths
from pusupu_jax.params import IMC_FORMS, ParameterError
from pusupu_jax.ros2 import JOINTS, check_joints

from .space import GROUPS

# the settings that the objective's traced program reads (pusupu_jax.tune.run.structure_key names its program by them):
# the tuned fields' groups and sharing name it through the space, the IMC form through the start point's structure;
# the paths, seeds, payloads and the start point's values enter as arguments; the optimiser's, the schedule's and the
# outputs' settings and the bounds are used on the host only
MAX_DRAWS = 256  # machines drawn per scenario at most (each is as much work as the scenario itself)

OBJECTIVE_SETTINGS = (
    "mode",
    "windows",
    "window_s",
    "aggregate",
    "weights",
    "force_peak_limit",
    "pm_min",
    "gm_min",
    "sharpness_force",
    "gradient",
    "remat",
)


@dataclass(frozen=True)
class TuneConfig:
    mode: str = "hybrid"
    imc_form: str = "full"
    groups: tuple = ("imc", "velocity", "hybrid")
    shared: bool = True
    trajectories: tuple = ("arc", "p2p")
    path_s: float | None = None
    windows: int = 6
    window_s: float = 0.5
    refresh_every: int = 5
    kin_error_seeds: tuple = (None,)
    payloads: tuple = (0.0,)
    draws: int = 0
    aggregate: str = "mean"
    iterations: int = 25
    learning_rate: float = 0.1
    final_lr_fraction: float = 1.0
    clip_norm: float = 1.0
    starts: int = 1
    start_spread: float = 0.3
    seed: int = 0
    checkpoint_every: int = 5
    weights: dict = field(default_factory=lambda: {"track_rms": 1.0, "balance": 0.1})
    force_peak_limit: float = 1.0
    pm_min: float = 45.0
    gm_min: float = 6.0
    sharpness_force: float = 1.0
    bounds: dict = field(default_factory=lambda: {"lambda2": (0.01, 0.5)})
    gradient: str = "reverse"
    remat: bool = False
    baselines: tuple = ("pid", "pid_ff")
    ros_joints: tuple = JOINTS

    @classmethod
    def quick(cls) -> "TuneConfig":
        """A smoke run: the arc's first 2 s in 2 windows of 0.3 s, 5 iterations, no baselines (no extra compile)."""
        return cls(
            trajectories=("arc",),
            path_s=2.0,
            windows=2,
            window_s=0.3,
            refresh_every=1,
            iterations=5,
            checkpoint_every=2,
            baselines=(),
        )

    @classmethod
    def load(cls, path, base: "TuneConfig | None" = None) -> "TuneConfig":
        names = [f.name for f in dataclasses.fields(cls)]
        data = read_yaml_mapping(Path(path), "key", names)
        if isinstance(data.get("trajectories"), list):  # path files named relative to the configuration
            data["trajectories"] = [
                paths.resolve(t, Path(path).parent) if isinstance(t, str) else t for t in data["trajectories"]
            ]
        try:
            cfg = (base or cls()).replace(**data)
            for k, spec in enumerate(data.get("trajectories") or ()):
                try:  # a missing or unreadable path file is named with its key here, not later on its own
                    paths.source_digest(spec)
                except ParameterError as e:
                    raise ParameterError(f"tune config trajectories[{k}]: {e}") from None
        except ParameterError as e:
            raise ParameterError(f"{path}: {e}") from None
        return cfg

    def replace(self, **changes) -> "TuneConfig":
        for key in ("groups", "trajectories", "kin_error_seeds", "payloads", "baselines", "ros_joints"):
            if key in changes and isinstance(changes[key], list):
                changes[key] = tuple(changes[key])
        if "bounds" in changes and isinstance(changes["bounds"], dict):
            changes["bounds"] = {k: tuple(v) if isinstance(v, list) else v for k, v in changes["bounds"].items()}
        out = dataclasses.replace(self, **changes)
        out.validate()
        return out

    def validate(self) -> None:
        """Every key's kind and range (one line naming the key); numbers must be finite unless a key says so."""

        def need(ok, key, expected, got):
            if not ok:
                raise ParameterError(f"tune config {key}: expected {expected}, got {inputs.shown(got)}")

        def num(key, **kw):
            inputs.number(getattr(self, key), f"tune config {key}", ParameterError, **kw)

        def integer(key, low=1):
            inputs.integer(getattr(self, key), f"tune config {key}", ParameterError, low=low)

        def names(key, allowed):
            v = getattr(self, key)
            need(
                isinstance(v, tuple) and v and set(v) <= set(allowed) and len(set(v)) == len(v),
                key,
                f"a list of distinct names from {sorted(allowed)}",
                v,
            )

        need(self.mode in TUNE_MODES, "mode", f"one of {tuple(map(str, TUNE_MODES))}", self.mode)
        names("groups", GROUPS)
        need(
            isinstance(self.trajectories, tuple) and self.trajectories,
            "trajectories",
            "a list of named paths or path files",
            self.trajectories,
        )
        for k, spec in enumerate(self.trajectories):
            paths.check_spec(spec, f"tune config trajectories[{k}]")
        labels = [paths.path_label(spec) for spec in self.trajectories]
        need(
            len(set(labels)) == len(labels),
            "trajectories",
            "distinct paths, distinctly named (a file is named by its stem)",
            self.trajectories,
        )
        need(
            isinstance(self.kin_error_seeds, tuple)
            and self.kin_error_seeds
            and all(
                s is None or (isinstance(s, int) and not isinstance(s, bool) and s >= 0) for s in self.kin_error_seeds
            ),
            "kin_error_seeds",
            "a list of null or non-negative integers",
            self.kin_error_seeds,
        )
        need(isinstance(self.payloads, tuple) and self.payloads, "payloads", "a list of masses [kg]", self.payloads)
        for k, p in enumerate(self.payloads):
            inputs.number(p, f"tune config payloads[{k}]", ParameterError, low=0.0, high=1000.0)
        inputs.integer(self.draws, "tune config draws", ParameterError, low=0, high=MAX_DRAWS)
        need(self.aggregate in ("mean", "max"), "aggregate", "mean or max", self.aggregate)
        num("final_lr_fraction", low=0.0, low_open=True, high=1.0)
        for key in ("learning_rate", "clip_norm", "sharpness_force", "force_peak_limit"):
            num(key, low=0.0, low_open=True)
        num("window_s", low=0.0, low_open=True, high=60.0)
        if self.path_s is not None:
            num("path_s", low=0.0, low_open=True, high=3600.0)
        num("pm_min", low=0.0, high=90.0)
        num("gm_min", low=0.0, high=60.0)
        num("start_spread", low=0.0)
        for key in ("iterations", "starts", "checkpoint_every", "windows", "refresh_every"):
            integer(key)
        integer("seed", low=None)
        need(isinstance(self.shared, bool), "shared", "true or false", self.shared)
        need(isinstance(self.remat, bool), "remat", "true or false", self.remat)
        need(
            isinstance(self.weights, dict) and set(self.weights) <= set(TERMS) and self.weights,
            "weights",
            f"a mapping of some of {TERMS} to non-negative numbers",
            self.weights,
        )
        for term, w in self.weights.items():
            inputs.number(w, f"tune config weights.{term}", ParameterError, low=0.0)
        need(
            control_mode(self.mode).hybrid or "hybrid" not in self.groups,
            "groups",
            "the 'hybrid' group only in hybrid mode",
            self.groups,
        )
        need(
            isinstance(self.bounds, dict) and all(isinstance(v, tuple) and len(v) == 2 for v in self.bounds.values()),
            "bounds",
            "a mapping of field names to [lower, upper]",
            self.bounds,
        )
        for field_name, pair in self.bounds.items():
            for k, v in enumerate(pair):
                inputs.number(v, f"tune config bounds.{field_name}[{k}]", ParameterError, low=0.0, low_open=True)
        need(self.gradient in GRADIENT_MODES, "gradient", f"one of {GRADIENT_MODES}", self.gradient)
        need(
            self.checkpoint_every % self.refresh_every == 0,
            "checkpoint_every",
            f"a multiple of refresh_every ({self.refresh_every})",
            self.checkpoint_every,
        )
        need(self.imc_form in IMC_FORMS, "imc_form", f"one of {IMC_FORMS}", self.imc_form)
        need(
            isinstance(self.baselines, tuple)
            and set(self.baselines) <= set(BASELINE_MODES)
            and len(set(self.baselines)) == len(self.baselines),
            "baselines",
            f"a list of distinct modes from {', '.join(BASELINE_MODES)}",
            self.baselines,
        )
        need(
            self.mode in (Mode.PID, Mode.PID_FF) or not {"pid", "feedforward"} & set(self.groups),
            "groups",
            "the pid and feedforward groups only in the pid and pid_ff modes",
            self.groups,
        )
        check_joints(self.ros_joints, "tune config ros_joints")  # the exporter's own rule, before any work

    def to_json(self) -> dict:
        """Every setting as JSON types (a report's ``config``, a batch shard's settings: ``TuneConfig().replace(**d)``
        reads it back)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self).items()}

    def digest(self) -> str:
        """A hash of every setting and of the path files' contents (the checkpoint and the gain file's provenance
        carry it)."""
        files = {spec: paths.source_digest(spec) for spec in self.trajectories if paths.is_path_file(spec)}
        text = json.dumps(
            dataclasses.asdict(self) | ({"path_files": files} if files else {}), sort_keys=True, default=str
        )
        return hashlib.sha256(text.encode()).hexdigest()[:16]
