"""The tuner: the optimiser on a synthetic problem, checkpoints, gain files and their validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pusupu_jax import AxisLoad, LoopRates, ParameterError, ServoParams, rollout
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.tune.optimise import optimise
from pusupu_jax.tune.space import Space

SERVO = ServoParams.table1()
RATES = LoopRates()


def _synthetic():
    """Single-axis plants following a 1 Hz sine with a step: the trace of known IMC gains is the target."""
    t = np.arange(600) * RATES.dt_position
    x = 0.01 * np.sin(2 * np.pi * t) + 0.005 * (t > 0.3)  # a sine and a step: both lambdas leave their mark
    ref = jnp.asarray(np.repeat(x[:, None], 6, axis=1) / (0.01 / (2 * np.pi)))
    truth = SERVO.replace(lambda1=np.full(6, 0.03), lambda2=np.full(6, 0.08))
    target = rollout(truth, AxisLoad.default(), ref).theta
    space = Space.create(("imc",), SERVO, HybridGains(), bounds={"lambda1": (0.005, 0.2), "lambda2": (0.02, 0.5)})

    def loss(z):
        servo, _ = space.apply(z)
        return jnp.mean((rollout(servo, AxisLoad.default(), ref).theta - target) ** 2) * 1e2, None

    return space, jax.jit(jax.value_and_grad(loss, has_aux=True))


@pytest.mark.slow
def test_tuner_recovers_known_gains_from_a_perturbed_start():
    """lambda1 0.018 -> 0.03 and lambda2 0.15 -> 0.08 recovered to 1 % (observed 0.004 % and 0.012 %) by clipped Adam
    on log-gains at the tuner's default learning rate, decayed to 2 % of it over 150 iterations."""
    space, vg = _synthetic()
    out = optimise(vg, space.z0(), space.project, iterations=150, learning_rate=0.1, final_lr_fraction=0.02)
    got = space.values(out.z)
    assert float(got["lambda1"]) == pytest.approx(0.03, rel=0.01)
    assert float(got["lambda2"]) == pytest.approx(0.08, rel=0.01)
    assert out.objective < 1e-3 * out.history[0].objective


def test_resuming_from_a_checkpoint_gives_the_uninterrupted_result(tmp_path):
    """Stop after 6 of 12 iterations (a checkpoint every 3), continue: the same bits as one run of 12."""
    space, vg = _synthetic()
    kw = dict(learning_rate=0.05, starts=2, start_spread=0.2, seed=4, checkpoint_every=3, digest="x")
    whole = optimise(vg, space.z0(), space.project, iterations=12, checkpoint=tmp_path / "a.npz", **kw)
    calls = []

    def interrupted(z):
        if len(calls) == 6:
            raise KeyboardInterrupt
        calls.append(1)
        return vg(z)

    with pytest.raises(KeyboardInterrupt):
        optimise(interrupted, space.z0(), space.project, iterations=12, checkpoint=tmp_path / "b.npz", **kw)
    resumed = optimise(vg, space.z0(), space.project, iterations=12, checkpoint=tmp_path / "b.npz", **kw)
    assert resumed.history == whole.history  # every entry, with plain Python numbers after the JSON
    assert all(type(h.start) is int and type(h.objective) is float for h in resumed.history)
    for name in whole.z:
        assert np.array_equal(np.asarray(resumed.z[name]), np.asarray(whole.z[name]))
    with pytest.raises(ParameterError, match="checkpoint of another configuration"):
        optimise(vg, space.z0(), space.project, iterations=12, checkpoint=tmp_path / "b.npz", **(kw | {"digest": "y"}))


def test_per_axis_space_tunes_each_axis_and_checks_bounds():
    space = Space.create(("imc", "hybrid"), SERVO, HybridGains(), shared=False)
    z = space.z0()
    assert z["lambda1"].shape == (6,) and z["c6"].shape == ()
    servo, hybrid = space.apply(space.project({**z, "lambda1": z["lambda1"] + jnp.arange(6.0) * 10}))
    assert np.allclose(servo.lambda1, np.minimum(0.018 * np.exp(np.arange(6.0) * 10), 0.18))  # clipped at start*10
    assert float(hybrid.c6) == pytest.approx(1000.0)
    with pytest.raises(ParameterError, match=r"bounds.lambda2: expected 0 < lower <= start"):
        Space.create(("imc",), SERVO, HybridGains(), shared=False, bounds={"lambda2": (0.2, 0.5)})
    with pytest.raises(ParameterError, match="differs between axes"):
        Space.create(("imc",), SERVO.replace(lambda1=np.linspace(0.01, 0.02, 6)), HybridGains())


@pytest.mark.parametrize(
    "text, message",
    [
        ("iterations: 0", "iterations: expected an integer >= 1"),
        ("groups: [imc, foo]", "groups: expected a list of distinct names from"),
        ("colour: red", "unknown key 'colour'"),
        ("mode: imc\ngroups: [hybrid]", "the 'hybrid' group only in hybrid mode"),
        ("weights: {speed: 1}", "weights: expected a mapping of some of"),
        ("aggregate: median", "aggregate: expected mean or max"),
        ("gradient: backward", "gradient: expected one of \\('reverse', 'forward'\\)"),
        ("remat: 1", "remat: expected true or false, got 1"),
        ("pm_min: -1000", "pm_min: expected a number >= 0"),
        ("pm_min: .nan", "pm_min: expected a finite number"),
        ("payloads: [.inf]", r"payloads\[0\]: expected a finite number"),
        ("weights: {track_rms: .inf}", "weights.track_rms: expected a finite number"),
        ("groups: [imc, imc]", "groups: expected a list of distinct names"),
        ("window_s: .inf", "window_s: expected a finite number"),
        ("path_s: .inf", "path_s: expected a finite number"),
        ("horizon_s: 2.0", "unknown key 'horizon_s'"),
        ("iterations: 2.5", "iterations: expected an integer"),
        ("learning_rate: '0.1'", "learning_rate: expected a number, got str"),
        ("checkpoint_every: 3", "checkpoint_every: expected a multiple of refresh_every"),
        ("imc_form: exact", "imc_form: expected one of"),
        ("baselines: [hybrid]", "baselines: expected a list of distinct modes"),
        ("ros_joints: [a, b]", "ros_joints: expected 6 distinct names of letters, digits and _"),
        ("a: &x 1\nb: *x", "anchors are not accepted"),
        ("draws: -1", r"draws: expected an integer in \[0, 256\], got -1"),
    ],
)
def test_bad_tune_configurations_are_rejected(tmp_path, text, message):
    from pusupu_jax.tune.config import TuneConfig

    path = tmp_path / "tune.yaml"
    path.write_text(text + "\n")
    with pytest.raises(ParameterError, match=message):
        TuneConfig.load(path)


def test_a_job_in_float32_is_refused_before_anything_runs(tmp_path):
    """Without float64 (a notebook that skipped ``setup_jax``) the job tuned in float32 for minutes and then failed in
    XLA's verifier at the stability check of the gains it would export (a float32 frequency grid sliced as float64).
    It is refused at once, saying what to call, and writes nothing."""
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.job import run_job

    with (
        jax.enable_x64(False),
        pytest.raises(
            RuntimeError,
            match=r"^pusupu tune's gradients and the stability check of the gains it exports compute in float64: call "
            r"pusupu_jax\.runtime\.setup_jax\(\) first$",
        ),
    ):
        run_job(TuneConfig(), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_tune_configuration_overrides_the_defaults(tmp_path):
    from pusupu_jax.tune.config import TuneConfig

    path = tmp_path / "tune.yaml"
    path.write_text("kin_error_seeds: [null, 3]\npayloads: [0.0, 10.0]\nbounds: {lambda1: [0.005, 0.3]}\n")
    cfg = TuneConfig.load(path)
    assert cfg.kin_error_seeds == (None, 3) and cfg.payloads == (0.0, 10.0)
    assert cfg.bounds == {"lambda1": (0.005, 0.3)} and cfg.iterations == TuneConfig().iterations
    assert cfg.digest() != TuneConfig().digest()


def test_draws_add_each_scenario_on_machines_drawn_from_the_identified_one_with_the_controller_told_it():
    """``draws: 2`` on a machine with an uncertainty section: each path and payload on the machine and on two drawn
    machines (the same two for each), every scenario with its drive values (PlantDrives: the plant's, not the
    controller's), the payloads drawn too; a machine without the section is refused in one line."""
    import dataclasses

    from pusupu_jax.machine_file import Machine
    from pusupu_jax.tune.config import TuneConfig
    from pusupu_jax.tune.run import scenario_list

    base = Machine.default()
    machine = dataclasses.replace(
        base, uncertainty={"viscous": np.full(6, 5.0), "payload_mass": np.array(0.3), "Kt": np.full(6, 0.02)}
    )
    cfg = TuneConfig(trajectories=("arc", "p2p"), payloads=(0.0, 10.0), draws=2)
    specs = scenario_list(cfg, machine)
    assert [s.name for s in specs[:6]] == [
        "arc",
        "arc/draw1",
        "arc/draw2",
        "arc/10kg",
        "arc/10kg/draw1",
        "arc/10kg/draw2",
    ]
    assert len(specs) == 12 and specs[6].name == "p2p"
    np.testing.assert_array_equal(specs[0].drives["viscous"], base.drives["viscous"])
    for a, b in ((1, 7), (2, 11), (1, 4)):  # the same drawn machine on every path and payload
        for k in ("viscous", "Kt", "Ke"):
            np.testing.assert_array_equal(specs[a].drives[k], specs[b].drives[k])
    assert not np.array_equal(specs[1].drives["viscous"], specs[2].drives["viscous"])
    np.testing.assert_array_equal(specs[1].drives["coulomb"], base.drives["coulomb"])  # no standard error: not drawn
    assert specs[4].options.payload == pytest.approx(10.0 + specs[1].options.payload)
    # the host's reference (hybrid's force feedforward) keeps the machine file's payload, not the drawn one
    assert specs[0].told is None and specs[1].told.payload == 0.0 and specs[4].told.payload == 10.0
    assert {s.options.payload for s in specs[1:3]} != {0.0}
    assert all(s.drives is None for s in scenario_list(TuneConfig(), machine))
    with pytest.raises(ParameterError, match="draws: expected a machine file with an uncertainty section"):
        scenario_list(cfg, base)


class _Stream:
    """A stream that records what is written; ``tty``: whether it says it is a terminal."""

    def __init__(self, tty: bool):
        self.tty, self.text = tty, ""

    def isatty(self):
        return self.tty

    def write(self, s):
        self.text += s

    def flush(self):
        pass


def _slow_first():
    """A quadratic's ``value_and_grad`` whose first evaluation takes 0.35 s (a compile) and the others 0.05 s."""
    import time

    calls = []

    def vg(z):
        time.sleep(0.35 if not calls else 0.05)
        calls.append(1)
        return jax.value_and_grad(lambda z: (jnp.sum((z["a"] - 1.0) ** 2), None), has_aux=True)(z)

    return vg


@pytest.mark.parametrize("tty", [False, True])
def test_progress_keeps_the_first_iteration_apart_from_the_rate(tty):
    """At a terminal (or in a notebook) a tqdm bar, in logs a line per iteration; both give the first iteration's
    time, which includes the compile, apart, and a rate and an ETA from the iterations after it."""
    from pusupu_jax.tune.progress import progress_reporter

    stream = _Stream(tty)
    optimise(
        _slow_first(),
        {"a": jnp.zeros(2)},
        lambda z: z,
        iterations=4,
        learning_rate=0.1,
        progress=progress_reporter(1, stream),
    )
    if not tty:
        lines = stream.text.splitlines()
        assert len(lines) == 4 and lines[0].startswith("tune [start 1/1] [#####...............] 1/4 J=2.0000")
        assert "first iteration (with the compile)" in lines[0] and "ETA" not in lines[0]
        rate = float(lines[-1].split(" s/it")[0].split()[-1])
        assert rate < 0.2 and lines[-1].endswith("ETA 0 s")  # the compile is not in the rate
    else:
        assert "\r" in stream.text and "4/4" in stream.text and "first iteration (with the compile)" in stream.text
        assert "it/s" in stream.text  # tqdm's rate over the iterations after the first: faster than 1 per second


def test_the_gradients_program_is_named_by_the_settings_it_reads_only():
    """Problems that differ in the optimiser's settings, the paths, seeds, payloads and start gains share one traced
    gradient program (the second process loads it from disk); a setting that the objective reads names a program of
    its own."""
    from pusupu_jax.tune.config import OBJECTIVE_SETTINGS, TuneConfig
    from pusupu_jax.tune.run import Problem, structure_key

    base = TuneConfig(trajectories=("p2p",), path_s=0.3, windows=2, window_s=0.1, baselines=())
    servo, hybrid = ServoParams.table1(), HybridGains()
    key = structure_key(Problem(base, servo, hybrid))
    same = base.replace(
        trajectories=("arc",), kin_error_seeds=(3,), payloads=(5.0,), iterations=7, learning_rate=0.02,
        refresh_every=3, starts=2, seed=4, checkpoint_every=6, baselines=("pid",), bounds={"lambda2": (0.02, 0.4)},
    )  # fmt: skip
    assert structure_key(Problem(same, servo, hybrid)) == key
    for change in ({"pm_min": 50.0}, {"weights": {"track_rms": 1.0, "balance": 0.2}}, {"aggregate": "max"}):
        assert set(change) <= set(OBJECTIVE_SETTINGS)
        assert structure_key(Problem(base.replace(**change), servo, hybrid)) != key, change
    # another start point, and another machine's drives, are the program's arguments; other tuned fields are not
    assert structure_key(Problem(base, servo.replace(Kv=servo.Kv * 1.1, R=servo.R * 2), hybrid)) == key
    assert structure_key(Problem(base.replace(groups=("imc", "velocity")), servo, hybrid)) != key


def test_a_scenarios_reference_is_kept_on_disk_and_read_back_bit_for_bit(tmp_path, monkeypatch):
    """``tune.run.kept_reference``: the first call runs ``machine_reference`` and keeps its arrays, a second one with
    the same arguments reads them back (no ``machine_reference``), equal bit for bit, in a position mode and in hybrid
    (a pytree of three arrays); other gains are another file; without ``keep`` it is computed and nothing is kept;
    a damaged file warns and is computed again."""
    from pusupu_jax.paths import platform_path_from
    from pusupu_jax.plant.geometry import Geometry
    from pusupu_jax.plant.model import ModelOptions
    from pusupu_jax.tune import run, starts

    monkeypatch.setattr(starts, "path_for", lambda digest: tmp_path / "starts" / f"{digest}.npz")
    calls = []
    computed = run.machine_reference
    monkeypatch.setattr(run, "machine_reference", lambda *a, **k: calls.append(a[2]) or computed(*a, **k))
    geom = Geometry.default()
    path = platform_path_from("arc", geom.home, RATES)[:200]
    for mode in ("imc", "hybrid"):
        first = run.kept_reference(SERVO, path, mode, ModelOptions(), RATES, geom)
        again = run.kept_reference(SERVO, path, mode, ModelOptions(), RATES, geom)
        want = computed(SERVO, path, mode, options=ModelOptions(), rates=RATES, geom=geom)
        assert calls.count(mode) == 1
        assert jax.tree.structure(again) == jax.tree.structure(want)
        for a, b, c in zip(jax.tree.leaves(first), jax.tree.leaves(again), jax.tree.leaves(want)):
            assert np.array_equal(a, c) and np.array_equal(b, c) and b.dtype == c.dtype
    run.kept_reference(SERVO.replace(lambda1=SERVO.lambda1 * 2), path, "imc", ModelOptions(), RATES, geom)
    assert calls.count("imc") == 2  # other gains: another reference, computed
    alone = run.kept_reference(SERVO, path, "imc", ModelOptions(), RATES, geom, keep=False)
    assert calls.count("imc") == 3  # without keep: computed, not read
    assert np.array_equal(alone, computed(SERVO, path, "imc", options=ModelOptions(), rates=RATES, geom=geom))
    kept = sorted((tmp_path / "starts").glob("*-reference.npz"))
    assert len(kept) == 3
    for damaged in kept:
        damaged.write_bytes(damaged.read_bytes()[:-10] + b"0123456789")
    with pytest.warns(UserWarning, match="fails its checksum"):
        for mode in ("imc", "hybrid"):
            again = run.kept_reference(SERVO, path, mode, ModelOptions(), RATES, geom)
    assert calls == ["imc", "hybrid", "imc", "imc", "imc", "hybrid"] and np.array_equal(again.theta, want.theta)
