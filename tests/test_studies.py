"""Runs as typed records, the one loader the stages and the studies share, and the studies'
rules: scripts import the package, never each other."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.config import PROJECT_ROOT
from pipeline.data.alignment import load_runs, runs_at_model_rate
from pipeline.data.runs import Run, runs_by_id
from pipeline.data.schemas import ALIGNED, write_table


def aligned_table() -> pd.DataFrame:
    """Two runs at 10 Hz: ``b`` (listed first) 1 s long, ``a`` 0.5 s; x = t, y = 2 t, z = -t;
    pressure 1 kPa on every valve until 0.3 s, then 3 kPa."""
    rows = []
    for run_id, duration in (("b", 1.0), ("a", 0.5)):
        t = np.round(np.arange(round(duration * 10) + 1) / 10, 10)
        p = np.where(t < 0.3, 1.0, 3.0)
        rows.append(pd.DataFrame({"run_id": run_id, "t": t, "p_0": p, "p_1": p, "p_2": p,
                                  "x": t, "y": 2 * t, "z": -t, "matched": t == 0.3}))
    return pd.concat(rows, ignore_index=True)


def test_runs_at_model_rate_are_records_with_named_arrays_and_units():
    runs = runs_at_model_rate(aligned_table(), 5.0)
    assert [run.run_id for run in runs] == ["a", "b"]  # sorted by run id
    a, b = runs
    assert isinstance(a, Run) and len(a) == 3 and len(b) == 6
    np.testing.assert_allclose(a.times_s, [0.0, 0.2, 0.4])
    assert a.times_s.dtype == np.float64
    assert a.pressures_kpa.dtype == np.float32 and a.positions_m.dtype == np.float32
    # pressures held (3 kPa from 0.3 s: the grid point at 0.4 s), positions interpolated
    np.testing.assert_array_equal(a.pressures_kpa[:, 0], [1.0, 1.0, 3.0])
    np.testing.assert_allclose(b.positions_m[-1], [1.0, 2.0, -1.0], rtol=1e-6)
    assert runs_by_id(runs)["b"] is b


def test_load_runs_reads_an_aligned_file_as_the_stages_do(tmp_path):
    path = tmp_path / "aligned.parquet"
    write_table(aligned_table(), path, ALIGNED, {}, {})
    read = load_runs(path, 5.0, "clock")
    direct = runs_at_model_rate(aligned_table(), 5.0, "clock")
    assert [run.run_id for run in read] == ["a", "b"]
    for one, other in zip(read, direct, strict=True):
        np.testing.assert_array_equal(one.pressures_kpa, other.pressures_kpa)
        np.testing.assert_array_equal(one.positions_m, other.positions_m)
        np.testing.assert_array_equal(one.times_s, other.times_s)


def test_a_run_refuses_arrays_of_other_lengths_and_replace_checks_again():
    times, pressures, positions = np.arange(4) / 10, np.zeros((4, 3)), np.zeros((4, 3))
    run = Run("r", times, pressures, positions)
    with pytest.raises(ValueError, match="positions_m"):
        Run("r", times, pressures, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="times_s must be"):
        Run("r", times[:2], pressures, positions)
    with pytest.raises(ValueError, match="positions_m"):
        run.replace(positions_m=np.zeros((4, 2)))
    shifted = run.replace(run_id="r@a", positions_m=positions + 0.001)
    assert shifted.run_id == "r@a" and run.positions_m.max() == 0.0  # a copy


def test_experiment_scripts_import_the_package_never_each_other():
    for path in sorted((PROJECT_ROOT / "experiments").glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                assert not name.startswith("experiments"), f"{path.name} imports {name}"


def test_value_iteration_knows_the_last_steps_by_hand():
    """On a coarse grid: with one step to go the value is the best immediate reward,
    -(angle^2 + 0.1 velocity^2) at torque 0; upright at rest stays upright at almost no cost
    (the grid's interpolation leaks a few thousandths over 200 steps)."""
    from pipeline.rl.pendulum_optimum import greedy_torque, solve

    optimum = solve(num_angles=32, num_velocities=21, num_torques=5)
    values = np.asarray(optimum.values)
    assert values.shape == (200, 32, 21)
    upright, quarter, rest = 16, 24, 10  # angles -pi + k pi/16; velocities -8 + 0.8 k
    assert values[-1, upright, rest] == pytest.approx(0.0, abs=1e-6)
    assert values[-1, quarter, rest] == pytest.approx(-(np.pi / 2) ** 2, rel=1e-5)
    assert values[-1, quarter, rest + 5] == pytest.approx(-(np.pi / 2) ** 2 - 0.1 * 4.0 ** 2,
                                                         rel=1e-5)
    assert values[0, upright, rest] == pytest.approx(0.0, abs=0.01)
    assert values[0, quarter, rest] < -(np.pi / 2) ** 2  # a quarter turn costs more than a step
    assert (values[0] <= 1e-6).all()  # no reward is positive
    no_future = np.zeros((32, 21), np.float32)
    assert float(greedy_torque(optimum, no_future, np.float32(np.pi / 2), np.float32(0))) == 0.0


@pytest.mark.slow
def test_recorded_runs_come_through_align_and_are_reused(tmp_path):
    from pipeline.studies import recorded_runs

    overrides = (f"paths.output_dir={tmp_path}", "experiment=quick", "robot.num_runs=2",
                 "exploration.num_steps=20")
    cfg, runs = recorded_runs(*overrides, rate_hz=5.0)
    assert Path(cfg.paths.output_dir) == tmp_path
    assert [run.run_id for run in runs] == ["sim-000", "sim-001"]
    assert all(isinstance(run, Run) for run in runs)
    np.testing.assert_allclose(np.diff(runs[0].times_s), 0.2)
    (aligned,) = (tmp_path / "artifacts" / "align").glob("[!.]*")
    again = load_runs(aligned / "aligned.parquet", 5.0)
    np.testing.assert_array_equal(again[1].positions_m, runs[1].positions_m)
    _, model_rate = recorded_runs(*overrides)  # the model's rate: dataset.model_hz, 10 Hz
    np.testing.assert_allclose(np.diff(model_rate[0].times_s), 0.1)
    assert len(list((tmp_path / "artifacts" / "align").glob("[!.]*"))) == 1  # reused


def test_a_study_reports_its_results_file_or_says_it_has_none(tmp_path, capsys):
    from argparse import Namespace

    from pipeline.studies import start_study

    out = tmp_path / "rows.jsonl"
    table = lambda path: f"table of {Path(path).name}"  # noqa: E731
    assert start_study(Namespace(report=False, out=str(out)), table) is False
    with pytest.raises(SystemExit, match=r"--report: no results file .*rows\.jsonl"):
        start_study(Namespace(report=True, out=str(out)), table)
    out.write_text("{}\n")
    assert start_study(Namespace(report=True, out=str(out)), table) is True
    assert capsys.readouterr().out == "table of rows.jsonl\n"
