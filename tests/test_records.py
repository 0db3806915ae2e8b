"""The typed records a run returns read back from the JSON they write: a machine run's metrics (with a hybrid run's
figures), and an optimiser history entry."""

import json

from pusupu_jax.machine import MachineRun
from pusupu_jax.metrics import HybridFigures, MachineMetrics, Metric
from pusupu_jax.tune.state import Evaluation

SIX = [0.5, 0.25, 0.125, 1.0, 2.0, 4.0]
HYBRID = HybridFigures("rms", {"m6": 20.0, "c6": 2000.0, "g": 100.0}, 35.0, 1.5, 4.0)
METRICS = MachineMetrics(3.0, 0.02, 0.04, SIX, [None, 0.1] + SIX[2:], SIX, [60.0, 64.0] + SIX[2:], 0.001, 1e-6, HYBRID)


def test_machine_metrics_read_back_from_their_json_in_the_order_sim_prints():
    d = json.loads(json.dumps(METRICS.to_json()))
    metrics = [m.value for m in Metric if m is not Metric.HIGHEST_BRANCH_FORCE_PEAK_N]
    assert list(d) == ["duration_s"] + metrics + ["hybrid"]
    assert d["hybrid"] == {"form": "rms", "m6": 20.0, "c6": 2000.0, "g": 100.0} | {
        "force_ff_peak_n": 35.0,
        "f_rho_rms_n": 1.5,
        "f_rho_peak_n": 4.0,
    }
    assert MachineMetrics.from_json(d) == METRICS
    # the reports' form: the highest branch force peak last, left out when read back
    with_highest = METRICS.to_json(highest_force=True)
    assert list(with_highest)[-1] == "highest_branch_force_peak_n" and with_highest[list(with_highest)[-1]] == 64.0
    assert MachineMetrics.from_json(with_highest) == METRICS
    assert METRICS.value(Metric.HIGHEST_BRANCH_FORCE_PEAK_N) == 64.0
    assert METRICS.value(Metric.BRANCH_REVERSAL_ERROR_MM)[0] is None


def test_a_machine_run_without_a_name_writes_no_name():
    run = MachineRun(None, "hybrid", "full", "rest", 3, 5.0, METRICS, 12.5)
    d = run.to_json()
    assert list(d)[:5] == ["mode", "imc_form", "start", "kin_error_seed", "payload_kg"] and d["wall_s"] == 12.5
    assert "name" not in d and MachineRun("seed3", *list(vars(run).values())[1:]).to_json()["name"] == "seed3"


def test_a_history_entry_reads_back_with_its_point_or_without():
    entry = Evaluation(1, 7, 0.25, {"lambda1": SIX, "T0": 0.001})
    assert Evaluation.from_json(json.loads(json.dumps(entry.to_json()))) == entry
    assert list(entry.to_json()) == ["start", "iteration", "objective", "z"]
    assert entry.without_point().to_json() == {"start": 1, "iteration": 7, "objective": 0.25}
