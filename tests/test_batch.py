"""Batch tuning (``pusupu batch``): job files, the vmapped batch against tuning alone, resuming, and Ray.

One small job file serves every test, so that the batch's gradient compiles once (the Ray
workers load it from the persistent cache): three scenarios that run (two seeds and payloads on
both paths, one with longer rods), one with a misspelt key and one whose home leaves the
workspace; two starts each; 3 iterations on two 0.1 s windows of the paths' first 0.3 s (the shape of
tests/test_cli.py's tune, so that tuning a job alone loads that command's compiled programs).
"""

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import jsonschema
import numpy as np
import pytest
import yaml

from pusupu_jax import devices, gains
from pusupu_jax.hybrid import HybridGains
from pusupu_jax.params import ServoParams
from pusupu_jax.tune import jobfile, run
from pusupu_jax.tune.batchjob import run_batch
from pusupu_jax.tune.run import Problem

pytestmark = pytest.mark.slow  # integration: every test here runs commands end to end

TUNE = {"iterations": 3, "refresh_every": 1, "checkpoint_every": 1, "windows": 2, "window_s": 0.1, "starts": 2}
SCENARIOS = [
    {"name": "arc-s1", "trajectory": "arc", "kin_error_seed": 1, "path_s": 0.3},
    {"name": "p2p-s2-5kg", "trajectory": "p2p", "kin_error_seed": 2, "payload": 5.0, "path_s": 0.3},
    {"name": "arc-long-rods", "trajectory": "arc", "geometry": {"rod_lengths": [0.905] * 6}, "path_s": 0.3},
    {"name": "typo", "trajectory": "arc", "payloda": 1.0},
    {"name": "too-low", "trajectory": "arc", "geometry": {"home": [0.0, 0.0, 0.3, 0.0, 0.0]}, "path_s": 0.3},
]
JOB = {"format": "pusupu-batch-1", "problems": "independent", "plots": False, "tune": TUNE, "scenarios": SCENARIOS}
RUNS = ["arc-s1", "p2p-s2-5kg", "arc-long-rods"]
SCHEMA = json.loads(jobfile.SCHEMA_FILE.read_text())


def _write(path: Path, doc) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """The job file run in this process: ``(job path, out, summary, status, progress text)``."""
    folder = tmp_path_factory.mktemp("batch")
    job = _write(folder / "job.yaml", JOB)
    log = _Log()
    summary, status = run_batch(job, folder / "out", stream=log)
    return job, folder / "out", summary, status, log.text


class _Log:
    def __init__(self):
        self.text = ""

    def write(self, s):
        self.text += s

    def flush(self):
        pass


def test_the_example_job_file_passes_the_schema_and_bad_ones_fail_both_checks(tmp_path):
    jsonschema.validate(JOB | {"scenarios": SCENARIOS[:3]}, SCHEMA)
    bad_docs = [
        (JOB | {"problems": "shared"}, "problems: expected one of"),
        (JOB | {"tune": {"trajectories": ["arc"]}}, "unknown key 'trajectories'"),
        (JOB | {"tune": {"iterations": 0}}, "iterations: expected an integer >= 1"),
        (JOB | {"scenarios": []}, "scenarios: expected a non-empty list"),
        (JOB | {"format": "pusupu-batch-9"}, "format: expected 'pusupu-batch-1'"),
        (JOB | {"problems": "robust", "name": [1, 2]}, r"name: expected letters, digits .* got \[1, 2\]"),
        (JOB | {"problems": "robust", "name": ".hidden"}, "name: expected letters, digits"),
    ]
    for doc, message in bad_docs:
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(doc, SCHEMA)
        with pytest.raises(jobfile.JobFileError, match=message):
            jobfile.read(_write(tmp_path / "bad.yaml", doc))
    (tmp_path / "junk.yaml").write_text("scenarios: [\n")
    with pytest.raises(jobfile.JobFileError, match="not valid YAML"):
        jobfile.read(tmp_path / "junk.yaml")


def test_scenario_errors_fail_their_own_job_only(tmp_path):
    """A misspelt key and a home out of the rails' stroke fail those jobs; the others are ready; a robust problem
    whose scenarios ask for different windows fails as a whole."""
    jf = jobfile.read(_write(tmp_path / "job.yaml", JOB))
    errors = {j.name: j.error for j in jf.jobs}
    assert [n for n, e in errors.items() if e is None] == RUNS
    assert "unknown key 'payloda'" in errors["typo"]
    assert "leaves the workspace" in errors["too-low"] and "out of stroke" in errors["too-low"]
    robust = JOB | {"problems": "robust", "scenarios": SCENARIOS[:2] + [SCENARIOS[0] | {"name": "x", "windows": 3}]}
    (job,) = jobfile.read(_write(tmp_path / "robust.yaml", robust)).jobs
    assert "one mode, windows and window_s" in job.error
    assert len(jobfile.groups(jf.jobs)) == 1  # the three runnable jobs share one compiled gradient


def test_a_job_file_names_the_machine_every_job_runs_on(tmp_path):
    """``machine:`` (relative to the job file's folder): every scenario takes that machine's geometry (with its own
    overrides) and payload (a scenario's payload adds to it, at the machine's centre of mass), the path checks take
    its drives, and the jobs' digests change with it; a missing or bad machine file fails the file in one line."""
    from pusupu_jax import machine_file

    example = Path(__file__).parent.parent / "docs" / "examples" / "machine_user.yaml"
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "mine.yaml").write_text(example.read_text())
    machine = machine_file.load(example)
    doc = JOB | {"machine": "robots/mine.yaml", "scenarios": SCENARIOS[:3]}
    jsonschema.validate(doc, SCHEMA)
    jf = jobfile.read(_write(tmp_path / "job.yaml", doc))
    builtin = jobfile.read(_write(tmp_path / "builtin.yaml", JOB | {"scenarios": SCENARIOS[:3]}))
    assert all(j.error is None and j.machine is not None for j in jf.jobs), [j.error for j in jf.jobs]
    arc, p2p, rods = (j.specs[0] for j in jf.jobs)
    np.testing.assert_array_equal(arc.geometry.rail_points, machine.geometry.rail_points)
    np.testing.assert_array_equal(rods.geometry.rod_lengths, [0.905] * 6)
    np.testing.assert_array_equal(rods.geometry.rail_points, machine.geometry.rail_points)
    assert arc.options.payload == machine.payload.mass and p2p.options.payload == machine.payload.mass + 5.0
    assert p2p.options.payload_com == tuple(machine.payload.com)
    assert {j.digest() for j in jf.jobs}.isdisjoint(j.digest() for j in builtin.jobs)
    for bad, message in (("robots/none.yaml", "machine: .*none.yaml"), (3, "machine: expected the name of a machine")):
        with pytest.raises(jobfile.JobFileError, match=message):
            jobfile.read(_write(tmp_path / "bad.yaml", doc | {"machine": bad}))


def test_a_scenario_may_name_its_own_machine(tmp_path):
    """A scenario's ``machine:`` puts its job on that machine in place of the file's: its geometry, payload and
    digest, in a group of its own (one set of drives per shard); a machine file that does not read fails that job
    alone; a robust problem over two machine files fails in one line."""
    from pusupu_jax import machine_file
    from pusupu_jax.machine_file import Machine

    example = Path(__file__).parent.parent / "docs" / "examples" / "machine_user.yaml"
    (tmp_path / "mine.yaml").write_text(example.read_text())
    (tmp_path / "builtin.yaml").write_text(machine_file.template())
    own = [SCENARIOS[0] | {"name": "arc-builtin", "machine": "builtin.yaml"}]
    broken = [SCENARIOS[0] | {"name": "arc-none", "machine": "none.yaml"}]
    doc = JOB | {"machine": "mine.yaml", "scenarios": SCENARIOS[:3] + own + broken}
    jsonschema.validate(doc, SCHEMA)
    jf = jobfile.read(_write(tmp_path / "job.yaml", doc))
    jobs = {j.name: j for j in jf.jobs}
    assert [n for n, j in jobs.items() if j.error is None] == RUNS + ["arc-builtin"], [j.error for j in jf.jobs]
    assert jobs["arc-none"].error.startswith("scenarios[4].machine: ") and "none.yaml" in jobs["arc-none"].error
    mine = machine_file.load(example)
    assert all(machine_file.digest(jobs[n].machine) == machine_file.digest(mine) for n in RUNS)
    assert jobs["arc-builtin"].machine is None  # the built-in machine, as a file without machine: has it
    spec = jobs["arc-builtin"].specs[0]
    np.testing.assert_array_equal(spec.geometry.rail_points, Machine.default().geometry.rail_points)
    assert spec.options.payload == Machine.default().payload.mass
    assert jobs["arc-builtin"].digest() != jobs["arc-s1"].digest()
    assert sorted(len(g) for g in jobfile.groups(jf.jobs).values()) == [1, 3]
    robust = JOB | {"problems": "robust", "machine": "mine.yaml", "scenarios": SCENARIOS[:2] + own}
    (job,) = jobfile.read(_write(tmp_path / "robust.yaml", robust)).jobs
    assert job.error.startswith("robust problems need one machine for every scenario"), job.error
    assert repr(mine.name) in job.error and repr(Machine.default().name) in job.error


def test_batch_writes_every_jobs_outputs_and_marks_the_failed_ones(batch):
    job, out, summary, status, log = batch
    assert status == 1 and summary["jobs"] == 5 and summary["ok"] == 3
    assert summary["failed"] == ["typo", "too-low"]
    rows = {r["job"]: r for r in summary["rows"]}
    for name in RUNS:
        assert rows[name]["status"] == "ok"
        assert rows[name]["objective_after"] < rows[name]["objective_before"]  # 3 iterations: a few % lower
        g = gains.load(out / "jobs" / name / "gains.yaml")  # checksum, values and margins checked on load
        assert g.mode == "hybrid"
        assert json.loads((out / "jobs" / name / "report.json").read_text())["status"] == "ok"
    assert (out / "summary.csv").read_text().count("\n") == 6
    assert "| typo | failed |" in (out / "summary.md").read_text()
    assert (out / "summary.png").stat().st_size > 10_000
    assert "first iteration (with the compile)" in log and "ETA" in log


def test_batch_equals_tuning_each_scenario_alone(batch, monkeypatch):
    """Each job's history and gains equal pusupu tune's optimiser run on that scenario alone, same seed and starts.

    Tolerance 1e-7 relative: the same operations, but vmapping over 6 members changes XLA's fusion and
    summation order (last-bit differences) and 3 Adam steps carry them on; measured 3e-10 on the gains.
    The two lone problems differ only in their scenarios, so they share one traced and compiled gradient
    (pusupu_jax.tune.run._shared_gradient): each still equals its own batch member.  A problem started elsewhere (here
    another current loop gain, which is not tuned) shares it as well, the start point being an argument, and its
    objective at the same gains differs (the program does not hold the first problem's start).  Built again
    with nothing in memory, a problem reads the traced program from disk (pusupu_jax.programs) instead of tracing, and
    the start states and terms at its start from the files the first problem kept (pusupu_jax.tune.starts): bit for
    bit those a forward pass and the gradient give.  benchmarks/batch_equivalence.py checks every scenario of a
    64-scenario batch the same way.
    """
    _, out, summary, _, _ = batch
    jf = jobfile.read(out.parent / "job.yaml")
    problems = []
    for job in [j for j in jf.jobs if j.name in ("arc-s1", "p2p-s2-5kg")]:
        cfg = job.config
        problems.append(problem := Problem(cfg, ServoParams.table1(), HybridGains(), specs=list(job.specs)))
        alone = problem.tune()
        report = json.loads((out / "jobs" / job.name / "report.json").read_text())
        assert [h["objective"] for h in report["history"]] == pytest.approx(
            [h.objective for h in alone.history], rel=1e-7
        )
        for field, value in problem.space.values(alone.z).items():
            assert np.ravel(report["result"][field])[0] == pytest.approx(float(np.ravel(value)[0]), rel=1e-7)
    assert problems[0]._value_and_grad is problems[1]._value_and_grad
    # another start point shares the program too: the start is its argument, and the objective moves with it
    elsewhere = Problem(
        cfg, ServoParams.table1().replace(Ki=ServoParams.table1().Ki * 1.1), HybridGains(), specs=list(job.specs)
    )
    assert elsewhere._value_and_grad is problems[1]._value_and_grad
    at = (problems[1].z0(), problems[1].start_baseline(), problems[1].starts, problems[1].windows)
    (J, _), _ = problems[1]._value_and_grad(*at, problems[1].space.start)
    (J_elsewhere, _), _ = problems[1]._value_and_grad(*at, elsewhere.space.start)
    assert abs(float(J_elsewhere) / float(J) - 1) > 1e-6, (J, J_elsewhere)
    # as a new process would: the gradient's traced program is read from disk, not traced, and gives the same numbers
    monkeypatch.setattr(run, "_GRADIENTS", {})
    again = Problem(cfg, ServoParams.table1(), HybridGains(), specs=list(job.specs))
    again.prepare(again.z0(), 0)  # as a tune's first iteration: the start states at z0, then the terms there
    args = (again.z0(), again.start_baseline(), again.starts, again.windows, again.space.start)
    got, want = again._value_and_grad(*args), problems[1]._value_and_grad(*args)
    assert again._value_and_grad.loaded == 1
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)))
    # the start's terms read from disk too (one gradient less), and the start states renewed at z0 once, not again
    # for the terms
    assert again.starts_loaded == 1 and again.baseline_loaded == 1
    assert all(np.array_equal(again.baseline[k], problems[1].baseline[k]) for k in again.baseline)
    whole = again.run_paths(again.z0())
    computed = jax.tree.map(lambda *c: np.concatenate(c), *[c for _, c in whole])
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(again.starts), jax.tree.leaves(computed)))
    # the refresh's forward pass stops at the last window's start: the same start states, bit for bit
    short = again.run_paths(again.z0(), starts_only=True)
    assert all(len(t.t) < len(full.t) for (t, _), (full, _) in zip(short, whole))
    shortened = jax.tree.map(lambda *c: np.concatenate(c), *[c for _, c in short])
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(shortened), jax.tree.leaves(computed)))
    # where the job computes on a GPU, its two paths run on the host's CPU (devices.forward_pass_devices): the same
    # start states, bit for bit, as host arrays that the gradient takes to its own device
    monkeypatch.setattr(devices, "chosen_devices", lambda: [_Gpu()])
    hosted = again.run_paths(again.z0())
    assert all(isinstance(x, np.ndarray) for x in jax.tree.leaves(hosted))
    on_host = jax.tree.map(lambda *c: np.concatenate(c), *[c for _, c in hosted])
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(on_host), jax.tree.leaves(computed)))


class _Gpu:
    """What :func:`pusupu_jax.devices.chosen_devices` gives where a job computes on a GPU: its platform."""

    platform = "gpu"


@pytest.mark.skipif(len(jax.devices()) < 2, reason="one CPU: one host device")
def test_a_jobs_gradient_laid_over_devices_is_its_gradient_on_one(batch):
    """A job tuned alone, its two windows laid over two devices (test_batch_equals_tuning_each_scenario_alone's
    problem), against the same job's member of the batch on one device (the batch's own program), at the start: the
    value to 1e-12 relative (at the start it is the weights' sum, 1.1: equal in both), each gradient component to 1e-9
    of the largest.  Observed: at most 4.4e-11 of the largest component (5e-12 on Kv's -0.116; 1e-9 relative on g's
    1.2e-8, the smallest).  Both programs are compiled already (the batch's is read from disk).  Not bit for bit: the
    gradient's sum over the windows is then an all-reduce across devices, in another order than one device's sum, and
    vmapping over the batch's members changes XLA's fusion."""
    from pusupu_jax.tune.batch import BatchProblem, lay_out

    _, out, _, _, _ = batch
    jobs = [j for j in jobfile.read(out.parent / "job.yaml").jobs if j.error is None]
    specs, problems = lay_out([list(j.specs) for j in jobs])  # as pusupu batch lays the jobs out
    one = BatchProblem(jobs[0].config, specs, problems, ServoParams.table1(), HybridGains())
    assert len(one.devices) == 1 and one.members[0] == (0, 0) and jobs[0].name == "arc-s1"
    spread = Problem(jobs[0].config, ServoParams.table1(), HybridGains(), specs=list(jobs[0].specs))
    assert spread.mesh is not None and spread.mesh.size == 2
    (v1, _), g1 = spread.value_and_grad(spread.z0())
    (_, aux), g2 = one.value_and_grad(one.z0())  # every member at the start: member 0 is the job's first start
    assert one._value_and_grad.loaded == 1  # the batch's traced program, from disk
    assert float(v1) == pytest.approx(float(aux["value"][0]), rel=1e-12)
    largest = max(float(np.max(np.abs(np.asarray(g1[k])))) for k in g1)
    for k in g1:
        assert np.max(np.abs(np.asarray(g1[k]) - np.asarray(g2[k])[0])) <= 1e-9 * largest, k
    # The devices meet only after the scans: a collective inside a loop's body would make every device wait on the
    # others at every step (the gains' gradient summed over the windows there left 14 cores no faster than 2).
    args = (spread.z0(), spread.start_baseline(), spread.starts, spread.windows, spread.space.start)
    text = spread._value_and_grad.lower(*args).compile().as_text()  # the compiled program, from the cache
    entry = text[text.index("\nENTRY ") :].split("\n}\n")[0]
    collectives = re.compile(r" (?:all-reduce|all-gather|collective-permute|all-to-all|reduce-scatter)(?:-start)?\(")
    assert len(collectives.findall(entry)) == len(collectives.findall(text)) > 0


def test_running_again_skips_the_finished_jobs(batch):
    job, out, summary, _, _ = batch
    log = _Log()
    again, status = run_batch(job, out, stream=log)
    assert "3 done before, 0 shard(s) to run" in log.text
    assert again["rows"] == json.loads(json.dumps(summary["rows"]))


def test_ray_retries_a_killed_worker_and_gives_the_in_process_summary(batch, tmp_path):
    """``pusupu batch --ray --workers 2 --cpus-per-task 2`` (a local Ray instance): the shard's worker is killed
    (SIGKILL) once it has checkpointed; Ray retries the task, the retry continues from the checkpoint, and every job's
    figures equal the in-process run's exactly: the workers run the programs this process compiled (from the
    persistent cache) on the same inputs.  A task of two CPUs has this process's two host devices, so the programs
    laid over them are the same ones: with the cache warm, the worker's first iteration took 26 s, against 69 s with
    one CPU a task, whose worker compiled those programs again (one run after the other on the 2-core CPU).

    Ray starts its workers at niceness 15 (``RAY_worker_niceness``), so beside the suite's other workers they got
    almost none of the two cores: in one run the first worker took 185 s for what its retry then did in 52 s, once
    the other tests had finished, and the last minutes ran on one core.  This run asks for niceness 0."""
    job, _, summary, _, _ = batch
    out = tmp_path / "ray_out"
    killed = []

    def kill_after_first_checkpoint():
        deadline = time.time() + 900
        while time.time() < deadline and not killed:
            for folder in out.glob("shards/*"):
                if (folder / "checkpoint.npz").exists() and (folder / "worker.pid").exists():
                    pid = int((folder / "worker.pid").read_text())
                    os.kill(pid, signal.SIGKILL)
                    killed.append((folder, pid))
                    return
            time.sleep(0.2)

    killer = threading.Thread(target=kill_after_first_checkpoint, daemon=True)
    killer.start()
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pusupu_jax.cli",
            "batch",
            str(job),
            "--out",
            str(out),
            "--ray",
            "--workers",
            "2",
            "--cpus-per-task",
            "2",
        ],
        capture_output=True,
        text=True,
        env=dict(os.environ, RAY_worker_niceness="0"),
        timeout=1500,
    )
    killer.join(timeout=1)
    assert killed, "the shard never checkpointed"
    folder, pid = killed[0]
    assert int((folder / "worker.pid").read_text()) != pid  # the retry ran in another worker
    assert r.returncode == 1, r.stderr[-2000:]  # two jobs failed to read, as in process
    got = {row["job"]: row for row in json.loads((out / "summary.json").read_text())["rows"]}
    for want in summary["rows"]:
        row = got[want["job"]]
        assert row["status"] == want["status"]
        for key, value in want.items():
            if isinstance(value, float) and np.isfinite(value):
                assert row[key] == value, key


def test_the_example_job_file_of_the_readme_reads():
    """docs/examples/batch.yaml, the README tour's batch, is a valid job file of two jobs."""
    from pathlib import Path

    job = jobfile.read(Path(__file__).parent.parent / "docs" / "examples" / "batch.yaml")
    assert [j.name for j in job.jobs] == ["arc-empty", "arc-5kg"]
