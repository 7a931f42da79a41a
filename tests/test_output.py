"""What the demos and benchmarks print says why: an estimate's kind and the reason it was refused or applied late,
rz marked where the pose did not observe it, benchmarks as labelled tables, a missing optional package in one line."""
import sys

import numpy as np
import pytest

from experiments import cli
from experiments.scenarios import print_estimates
from experiments.timing_tools import print_table
from rme import Estimate


def estimate(t, applied, kind, accepted=True, reason="", rz_seen=False):
    e = Estimate(mean=np.array([0.9, 0.05, -0.03, 0.1]), std=np.full(4, 0.01), cov=np.eye(4), prior=np.zeros(4),
                 observed=np.array([True, True, True, rz_seen]), seconds=0.003, iterations=5, converged=True)
    e.t, e.applied, e.kind, e.accepted, e.reason = t, applied, kind, accepted, reason
    return e


def test_each_estimate_prints_its_kind_its_reason_and_an_unobserved_rz(capsys):
    t = np.arange(0, 5, 1e-3)
    log = {"t": t, "theta": np.zeros((len(t), 4)), "history": [
        estimate(1.2, 3.5, "detection", reason="held as a possible press on the hand"),
        estimate(2.0, np.nan, "detection", accepted=False, reason="explains only 40 % of the change"),
        estimate(4.0, 4.004, "at rest", rz_seen=True)]}
    print_estimates(log)
    lines = capsys.readouterr().out.strip().splitlines()
    assert "[detection]" in lines[0] and "applied at 3.500 s (held as a possible press on the hand)" in lines[0]
    assert "refused: explains only 40 % of the change" in lines[1]
    assert "[at rest]" in lines[2]
    assert ["(rz: prior, not observed at this pose)" in line for line in lines] == [True, True, False]


def test_a_table_has_its_title_header_aligned_rows_and_how_to_read_it(capsys):
    print_table("title", ["name", "time [ms]"], [["a", "1.25"], ["longer name", "10.00"]], "read it so.")
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "title" and "time [ms]" in lines[1] and lines[-1].strip() == "read it so."
    assert len({len(line) for line in lines[1:4]}) == 1          # the columns line up


def test_qp_bench_without_quadprog_is_one_line(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "quadprog", None)          # import quadprog now raises ModuleNotFoundError
    with pytest.raises(SystemExit) as stop:
        cli.main(["qp-bench"])
    assert "quadprog" in str(stop.value.code) and "\n" not in str(stop.value.code)


def test_franka_help_is_whole_and_names_no_internal_constant(capsys):
    import franka
    with pytest.raises(SystemExit):
        franka.main(["--help"])
    out = capsys.readouterr().out
    assert "SIM_COM" not in out and "(--sim)." in " ".join(out.split())   # the description's whole first sentence


def test_network_bench_labels_the_weights_files_training_time_as_recorded_not_measured(capsys):
    from experiments.training import print_benchmark
    r = {"forward_median_us": 143.44, "features_median_us": 414.3, "train_step_median_us": 91000.0,
         "train_samples_per_s": 351.6, "training_seconds": 135.32005159100027, "data_seconds": 32.17, "iterations": 7756,
         "epochs": 554, "val_mse": [0.0019, 0.00078, 0.00043, 0.0021]}
    print_benchmark(r, "weights.npz")
    out = capsys.readouterr().out
    assert "135.32005" not in out and "recorded in weights.npz by the run that trained it (not measured now)" in out
    assert "measured in this run" in out and "median [us]" in out


@pytest.mark.slow
def test_a_load_centred_below_the_flange_is_applied_as_soon_as_one_off_that_line():
    """A load centred below the flange looks like a hand pressing on it: the model takes it for the load it looks
    like within 0.5 s, as it does a load off that line (seeded plants)."""
    from experiments import scenarios
    for seed, r in ((3, (0.0, 0.0, 0.12)), (4, (0.05, -0.03, 0.12))):
        rec = scenarios.run(scenarios.Args(seed=seed), 2.5, [(1.0, np.array([0.45, *r]), None)])
        first = next(e for e in rec.history if e.accepted)
        assert first.kind == "detection" and first.applied - 1.0 < 0.5 and abs(first.mean[0] - 0.45) < 0.05
