"""Alignment on hand-made streams with known answers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from pipeline.data.alignment import align_run, align_tables, resample
from pipeline.data.schemas import ALIGNED, DataError, validate

SETTINGS = SimpleNamespace(max_match_dt_s=0.05, max_gap_s=0.25, gap_policy="error",
                           resample_hz=None)


def mocap(n=100, invalid=(), run_id="r"):
    t = np.round(np.arange(n) * 0.01, 10)
    frame = pd.DataFrame({"run_id": run_id, "t": t, "x": t, "y": 2 * t, "z": -t,
                          "valid": True})
    frame.loc[list(invalid), ["x", "y", "z"]] = np.nan
    frame.loc[list(invalid), "valid"] = False
    return frame


def commands(times, values=None, run_id="r"):
    values = values if values is not None else [[i + 1.0] * 3 for i in range(len(times))]
    values = np.asarray(values, float)
    return pd.DataFrame({"run_id": run_id, "t": times, "p_cmd_0": values[:, 0],
                         "p_cmd_1": values[:, 1], "p_cmd_2": values[:, 2]})


def settings(**changes):
    return SimpleNamespace(**{**vars(SETTINGS), **changes})


def test_commands_match_the_nearest_frame_and_are_held_until_the_next():
    aligned, (counts,) = align_run(commands([0.103, 0.498, 0.7549]), mocap(), SETTINGS)
    validate(aligned, ALIGNED, "test")
    # rows before the first command (frames 0-9) are dropped
    assert aligned["t"].iloc[0] == pytest.approx(0.10)
    assert len(aligned) == 90
    p0 = aligned["p_0"].to_numpy()
    np.testing.assert_array_equal(p0[:40], 1.0)  # frames 10..49
    np.testing.assert_array_equal(p0[40:65], 2.0)  # frames 50..74 (0.498 -> 0.50)
    np.testing.assert_array_equal(p0[65:], 3.0)  # frames 75..99 (0.7549 -> 0.75, not 0.76)
    assert aligned.loc[aligned["matched"], "t"].round(2).tolist() == [0.10, 0.50, 0.75]
    assert counts == {"commands": 3, "matched": 3, "overridden": 0, "unmatched": 0,
                      "frames": 100, "before_first_command": 10, "rows": 90, "filled": 87,
                      "interpolated": 0, "gaps": 0, "dropped_frames": 0}
    # positions are the mocap's own
    np.testing.assert_allclose(aligned["x"], aligned["t"])


def test_far_commands_are_unmatched_and_same_frame_commands_overridden():
    cmd = commands([0.103, 0.301, 0.304, 1.5])
    aligned, (counts,) = align_run(cmd, mocap(), SETTINGS)
    assert counts["matched"] == 2 and counts["overridden"] == 1 and counts["unmatched"] == 1
    # the later of the two commands on frame 30 wins
    assert aligned.loc[np.isclose(aligned["t"], 0.30), "p_0"].item() == 3.0
    assert aligned["p_0"].max() == 3.0  # the command at 1.5 s never takes effect


def test_short_mocap_gaps_are_interpolated_and_counted():
    aligned, (counts,) = align_run(commands([0.0]), mocap(invalid=range(20, 25)), SETTINGS)
    assert counts["dropped_frames"] == 5 and counts["interpolated"] == 5
    assert len(aligned) == 100 and np.isfinite(aligned[["x", "y", "z"]]).all().all()
    np.testing.assert_allclose(aligned["x"], aligned["t"], atol=1e-12)  # linear is exact here


def test_invalid_frames_at_the_edges_are_dropped():
    aligned, (counts,) = align_run(commands([0.0]), mocap(invalid=[0, 1, 2, 99]), SETTINGS)
    assert aligned["t"].iloc[0] == pytest.approx(0.03) and aligned["t"].iloc[-1] == 0.98
    assert counts["dropped_frames"] == 4 and counts["interpolated"] == 0


def test_a_long_gap_is_an_error_naming_the_run_and_time():
    with pytest.raises(DataError, match=r"run 'r'.*0\.410 s after t=0\.390") as err:
        align_run(commands([0.0]), mocap(invalid=range(40, 80)), SETTINGS, source="f.parquet")
    assert err.value.source == "f.parquet" and err.value.row == 39


def test_a_long_gap_splits_the_run_on_request():
    cmd = commands([0.0, 0.2, 0.9])
    aligned, counts = align_run(cmd, mocap(invalid=range(40, 80)), settings(gap_policy="split"))
    assert aligned["run_id"].unique().tolist() == ["r#0", "r#1"]
    second = aligned[aligned["run_id"] == "r#1"]
    assert second["t"].iloc[0] == pytest.approx(0.80)
    # the command sent at 0.2 s is still in force after the gap, until the one at 0.9 s
    np.testing.assert_array_equal(second["p_0"].to_numpy()[:10], 2.0)
    np.testing.assert_array_equal(second["p_0"].to_numpy()[10:], 3.0)
    assert [c["gaps"] for c in counts] == [1, 1]


def test_resampling_holds_pressures_and_interpolates_positions():
    aligned, _ = align_run(commands([0.103, 0.498, 0.7549]), mocap(), SETTINGS)
    coarse = resample(aligned, 10.0)
    validate(coarse, ALIGNED, "test")
    np.testing.assert_allclose(coarse["t"], np.arange(1, 10) / 10)
    assert coarse["p_0"].tolist() == [1, 1, 1, 1, 2, 2, 2, 3, 3]
    assert coarse["matched"].tolist() == [True, False, False, False, True, False, False, True,
                                          False]
    np.testing.assert_allclose(coarse["x"], coarse["t"], atol=1e-12)


def test_align_tables_handles_several_runs_and_reports_each():
    cmd = pd.concat([commands([0.0], run_id="a"), commands([0.5], run_id="b")])
    mo = pd.concat([mocap(run_id="a"), mocap(run_id="b")])
    aligned, report = align_tables(cmd, mo, settings(resample_hz=None))
    assert report["run_id"].tolist() == ["a", "b"]
    assert report["rows"].tolist() == [100, 50]
    assert len(aligned) == 150


def test_a_run_without_commands_is_an_error():
    with pytest.raises(DataError, match="run 'b' has mocap frames but no commands"):
        align_tables(commands([0.0], run_id="a"), mocap(run_id="b"), SETTINGS)


def test_command_locked_grid_puts_every_command_on_a_grid_point():
    from pipeline.data.alignment import resample_command_locked

    # commands 0.5 s apart but drifting against the 10 Hz clock (0.503 s periods)
    times = [0.103 + 0.503 * i for i in range(3)]
    aligned, _ = align_run(commands(times), mocap(n=200), SETTINGS)
    coarse = resample_command_locked(aligned, 10.0)
    validate(coarse, ALIGNED, "test")
    starts = coarse.loc[coarse["matched"], "t"].to_numpy()
    np.testing.assert_allclose(starts, [0.10, 0.61, 1.11])  # the frames the commands matched
    assert coarse["matched"].sum() == 3
    # 5 equal steps per 0.5 s command period, the last interval up to the end of the run
    first_period = coarse[(coarse["t"] >= 0.10) & (coarse["t"] < 0.61)]
    assert len(first_period) == 5 and (first_period["p_0"] == 1.0).all()
    np.testing.assert_allclose(np.diff(first_period["t"]), 0.102)
    assert coarse["p_0"].tolist()[5:10] == [2.0] * 5
    np.testing.assert_allclose(coarse["x"], coarse["t"], atol=1e-12)
