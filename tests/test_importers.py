"""Importers on the real recordings, PlotJuggler exports, and bad input."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from pipeline.data.alignment import align_run
from pipeline.data.importers import read_plotjuggler_csv, read_sorolex_csv
from pipeline.data.schemas import DataError
from pipeline.infra.artifacts import ArtifactStore
from pipeline.keys import key
from pipeline.stages.collect import collect

LIMITS = SimpleNamespace(p_min=-3.0, p_max=7.0, sum_max=13.0, preload=2.0)
SETTINGS = SimpleNamespace(max_match_dt_s=0.05, max_gap_s=0.25, gap_policy="error",
                           resample_hz=None)


def test_every_real_run_imports_and_aligns_back_to_the_original(sorolex_dir):
    files = sorted(sorolex_dir.glob("Step_control_*.csv"))
    assert len(files) == 7
    for path in files:
        original = pd.read_csv(path)
        commands, mocap = read_sorolex_csv(path, LIMITS)
        assert len(mocap) == len(original) and mocap["valid"].all()
        assert commands["run_id"].iloc[0] == path.stem
        # commands change at about 2 Hz
        assert np.median(np.diff(commands["t"])) == pytest.approx(0.5, abs=0.02)
        assert np.median(np.diff(mocap["t"])) == pytest.approx(0.01, abs=0.001)
        # the walk starts at the 2 kPa preload
        np.testing.assert_array_equal(commands.iloc[0, 2:].to_numpy(float), 2.0)
        # aligning the recovered streams reproduces the authors' alignment exactly
        aligned, (counts,) = align_run(commands, mocap, SETTINGS, str(path))
        assert counts["unmatched"] == 0 and counts["overridden"] == 0
        np.testing.assert_array_equal(
            aligned[["p_0", "p_1", "p_2"]].to_numpy(),
            original[[f"control_pressure_{j}" for j in range(3)]].to_numpy())
        np.testing.assert_array_equal(aligned["x"].to_numpy(), original["1_x"].to_numpy())


def test_real_positions_are_in_metres_with_y_vertical(sorolex_dir):
    _, mocap = read_sorolex_csv(sorolex_dir / "Step_control_17_10_12_20.csv", LIMITS)
    assert 0.010 < mocap["x"].min() < mocap["x"].max() < 0.056
    assert 0.350 < mocap["y"].min() < mocap["y"].max() < 0.362


# ---------------------------------------------------------------------------------------------
# bad input: each case names the file, the column and the row (or line)
# ---------------------------------------------------------------------------------------------
HEADER = "time,1_x,1_y,1_z,control_pressure_0,control_pressure_1,control_pressure_2\n"


def good_rows(n=20):
    return "".join(f"{100 + 0.01 * i:.2f},0.03,0.353,0.2,2.0,2.0,{2.0 + (i >= 10)}\n"
                   for i in range(n))


def write(tmp_path, text, name="run.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_good_small_file_imports(tmp_path):
    commands, mocap = read_sorolex_csv(write(tmp_path, HEADER + good_rows()), LIMITS)
    assert len(mocap) == 20 and len(commands) == 2
    assert commands["t"].tolist() == [100.0, 100.1]


@pytest.mark.parametrize(
    ("text", "pattern", "column", "row"),
    [
        ("", "empty", None, None),
        (HEADER, "no data rows", None, None),
        (HEADER.replace(",1_z", "") + good_rows(), r"missing column\(s\) \['1_z'\]", "1_z", None),
        (HEADER + good_rows()[:-12] + "\n", "truncated last line", "control_pressure_0", 19),
        (HEADER + good_rows().replace("100.14,0.03,0.353", "100.14,0.03,nan"),
         "not a finite number", "1_y", 14),
        (HEADER + good_rows().replace("100.05", "100.04"), "duplicate timestamp", "time", 5),
        (HEADER + good_rows().replace("100.05", "100.01"), "backwards", "time", 5),
        (HEADER + good_rows().replace("2.0,2.0,3.0", "2.0,7.5,3.0", 1), "above p_max",
         "control_pressure_1", 10),
        (HEADER + good_rows().replace("2.0,2.0,3.0", "6.0,6.0,3.0", 1), "exceeds sum_max", None, 10),
    ],
    ids=["empty", "header-only", "missing-column", "truncated", "nan", "duplicate-time",
         "backwards-time", "above-limit", "sum-above-limit"],
)
def test_bad_input_names_file_column_and_row(tmp_path, text, pattern, column, row):
    path = write(tmp_path, text)
    with pytest.raises(DataError, match=pattern) as err:
        read_sorolex_csv(path, LIMITS)
    assert str(path) in str(err.value)
    if column is not None:
        assert err.value.column == column and f"'{column}'" in str(err.value)
    if row is not None:
        assert err.value.row == row and f"row {row}" in str(err.value)


# ---------------------------------------------------------------------------------------------
# PlotJuggler CSV export of the ROS topics
# ---------------------------------------------------------------------------------------------
BODY = "/mocap_rigid_bodies/rigid_bodies.1/pose_stamped/pose/position"
PRESSURE = "/control_pressure/p_d"


def plotjuggler_frame():
    """Poses at 100 Hz and commands at 2 Hz merged on one time axis, as PlotJuggler exports."""
    t_pose = 50.0 + np.arange(150) * 0.01
    t_cmd = 50.0 + np.array([0.003, 0.503, 1.003])
    pose = pd.DataFrame({"__time": t_pose, f"{BODY}/x": 0.03, f"{BODY}/y": 0.353,
                         f"{BODY}/z": 0.2 + t_pose - 50})
    cmd = pd.DataFrame({"__time": t_cmd, **{f"{PRESSURE}.{j}": [2.0, 3.0, 4.0]
                                             for j in range(3)}})
    return pd.concat([pose, cmd]).sort_values("__time").reset_index(drop=True)


def test_plotjuggler_export_imports_and_aligns(tmp_path):
    path = tmp_path / "pj.csv"
    plotjuggler_frame().to_csv(path, index=False)
    commands, mocap = read_plotjuggler_csv(path, LIMITS)
    assert len(mocap) == 150 and len(commands) == 3
    assert commands["p_cmd_2"].tolist() == [2.0, 3.0, 4.0]
    aligned, (counts,) = align_run(commands, mocap, SETTINGS)
    assert counts["matched"] == 3 and aligned["p_0"].iloc[-1] == 4.0
    np.testing.assert_allclose(aligned.loc[aligned["matched"], "t"], [50.0, 50.5, 51.0])


def test_plotjuggler_partial_sample_and_missing_topic_are_errors(tmp_path):
    frame = plotjuggler_frame()
    frame.loc[3, f"{BODY}/y"] = np.nan
    path = tmp_path / "pj.csv"
    frame.to_csv(path, index=False)
    with pytest.raises(DataError, match="pose sample with an empty field") as err:
        read_plotjuggler_csv(path, LIMITS)
    assert err.value.column == f"{BODY}/y"
    frame = plotjuggler_frame().drop(columns=[f"{PRESSURE}.2"])
    frame.to_csv(path, index=False)
    with pytest.raises(DataError, match="pressure topic"):
        read_plotjuggler_csv(path, LIMITS)


# ---------------------------------------------------------------------------------------------
# more bad input, each with a known answer
# ---------------------------------------------------------------------------------------------
def test_a_nan_mid_file_is_not_called_a_truncated_line(tmp_path):
    path = write(tmp_path, HEADER + good_rows().replace("100.14,0.03,0.353", "100.14,0.03,nan"))
    with pytest.raises(DataError) as err:
        read_sorolex_csv(path, LIMITS)
    assert str(err.value) == (f"{path}, column '1_y', row 14: not a finite number: 'nan' "
                              f"(line 16)")


def test_a_file_cut_inside_its_last_number_drops_that_line(tmp_path):
    """The last line lost its final newline and the end of a number: 3.5 kPa reads as 3."""
    rows = good_rows().replace("2.0,2.0,3.0\n", "2.0,2.0,3.5\n")
    path = write(tmp_path, HEADER + rows[:-3])  # "...,2.0,2.0,3"
    notes = {}
    commands, mocap = read_sorolex_csv(path, LIMITS, notes=notes)
    assert notes == {"incomplete_last_line": 1}
    assert len(mocap) == 19 and mocap["t"].iloc[-1] == pytest.approx(100.18)
    assert commands["p_cmd_2"].tolist() == [2.0, 3.5]
    complete = {}
    read_sorolex_csv(write(tmp_path, HEADER + rows, "whole.csv"), LIMITS, notes=complete)
    assert complete == {"incomplete_last_line": 0}


def test_the_dropped_line_is_counted_in_the_collect_summary(tmp_path, make_cfg):
    data = tmp_path / "data"
    data.mkdir()
    (data / "cut.csv").write_text(HEADER + good_rows()[:-3])
    (data / "whole.csv").write_text(HEADER + good_rows())
    cfg = make_cfg("robot=sorolex_csv", f"robot.data_dir={data}", "robot.pattern=*.csv")
    summary = collect(cfg).manifest["summary"]
    assert summary["incomplete_lines_dropped"] == {"cut": 1}
    assert summary["frames"] == 39


def test_extra_valve_columns_are_refused_with_the_columns_found(tmp_path):
    header = HEADER.rstrip("\n") + ",control_pressure_3\n"
    rows = "".join(line + ",2.0\n" for line in good_rows().splitlines())
    path = write(tmp_path, header + rows)
    with pytest.raises(DataError) as err:
        read_sorolex_csv(path, LIMITS)
    assert str(err.value) == (
        f"{path}: found pressure columns ['control_pressure_0', 'control_pressure_1', "
        f"'control_pressure_2', 'control_pressure_3']; expected exactly ['control_pressure_0', "
        f"'control_pressure_1', 'control_pressure_2'] (3 valves)")


@pytest.mark.parametrize(("content", "message"), [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "a binary file, not a CSV text file"),
    (HEADER.replace("time", "temps_\xe9").encode("latin-1") + good_rows().encode(),
     "not a UTF-8 text file: byte 0xe9 at offset 6 is not UTF-8"),
])
def test_binary_and_non_utf8_files_are_named(tmp_path, content, message):
    path = tmp_path / "run.csv"
    path.write_bytes(content)
    with pytest.raises(DataError) as err:
        read_sorolex_csv(path, LIMITS)
    assert str(err.value).startswith(f"{path}: {message}")


def test_positions_in_millimetres_are_recognised(tmp_path, make_cfg):
    data = tmp_path / "data"
    data.mkdir()
    (data / "mm.csv").write_text(HEADER + good_rows().replace("0.03,0.353,0.2", "30,353,200"))
    cfg = make_cfg("robot=sorolex_csv", f"robot.data_dir={data}", "robot.pattern=*.csv")
    with pytest.raises(DataError) as err:
        collect(cfg)
    assert str(err.value) == (
        "run mm (mm.csv): positions look like millimetres, not metres: largest |x|, |y|, |z| = "
        "30, 353, 200, outside robot.workspace [[-3.0, -3.0, -3.0], [3.0, 3.0, 3.0]] m; convert "
        "the positions to metres")
    assert not ArtifactStore(cfg.paths.artifact_dir).find("collect", key("collect", cfg))


def test_positions_outside_the_workspace_but_not_millimetres(tmp_path, make_cfg):
    data = tmp_path / "data"
    data.mkdir()
    (data / "far.csv").write_text(HEADER + good_rows().replace("0.03,0.353,0.2", "0.03,0.353,5000.2"))
    cfg = make_cfg("robot=sorolex_csv", f"robot.data_dir={data}", "robot.pattern=*.csv")
    with pytest.raises(DataError, match=r"position \[0\.03, 0\.353, 5000\.2\] m lies outside "
                                        r"robot\.workspace"):
        collect(cfg)


def test_plotjuggler_extra_field_is_refused_with_the_fields_found(tmp_path):
    frame = plotjuggler_frame()
    frame[f"{PRESSURE}.3"] = frame[f"{PRESSURE}.0"]
    path = tmp_path / "pj.csv"
    frame.to_csv(path, index=False)
    with pytest.raises(DataError) as err:
        read_plotjuggler_csv(path, LIMITS)
    fields = [f"{PRESSURE}.{j}" for j in range(4)]
    assert str(err.value) == (f"{path}: the pressure topic has 4 field(s) {fields}; expected "
                              f"p_d.0..2 (or data.0..2): 3 valves")


def test_plotjuggler_missing_field_names_the_fields_that_exist(tmp_path):
    frame = plotjuggler_frame().drop(columns=[f"{PRESSURE}.2"])
    path = tmp_path / "pj.csv"
    frame.to_csv(path, index=False)
    with pytest.raises(DataError) as err:
        read_plotjuggler_csv(path, LIMITS)
    fields = [f"{PRESSURE}.{j}" for j in range(2)]
    assert str(err.value) == (f"{path}: the pressure topic has 2 field(s) {fields}; expected "
                              f"p_d.0..2 (or data.0..2): 3 valves")
    assert "found none" not in str(err.value)


def test_plotjuggler_errors_name_the_csv_line(tmp_path):
    frame = plotjuggler_frame()
    # the 41st pose goes back in time; it lies on CSV line 2 + its row in the merged table
    pose_rows = frame.index[frame[f"{BODY}/x"].notna()]
    row = int(pose_rows[40])
    frame.loc[row, "__time"] = frame.loc[int(pose_rows[39]), "__time"] - 0.001
    path = tmp_path / "pj.csv"
    frame.to_csv(path, index=False)
    with pytest.raises(DataError) as err:
        read_plotjuggler_csv(path, LIMITS)
    assert row != 40 and err.value.row == row
    assert str(err.value).endswith(f"(line {row + 2})")
    assert "pose topic: timestamp goes backwards" in str(err.value)


def test_frames_hold_the_command_sent_last_at_its_recorded_time():
    from pipeline.stages.collect import frame_commands

    index = frame_commands(np.array([0.0, 0.5, 1.2]), 200, 100.0)
    expected = np.r_[np.zeros(50), np.ones(70), np.full(80, 2)]
    np.testing.assert_array_equal(index, expected)


def test_a_simulated_arm_replays_the_recorded_commands_at_their_times(tmp_path, make_cfg):
    data = tmp_path / "data"
    data.mkdir()
    rows = "".join(f"{50 + 0.01 * i:.2f},0.03,0.353,0.2,{2.0 - 3.0 * (i >= 120):.1f},2.0,"
                   f"{2.0 + (i >= 40)}\n" for i in range(300))
    (data / "a.csv").write_text(HEADER + rows)
    (data / "b.csv").write_text(HEADER + good_rows(150))
    cfg = make_cfg("robot=sim_sorolex_replay", f"robot.replay.data_dir={data}",
                   "robot.replay.pattern=*.csv")
    artifact = collect(cfg)
    commands = pd.read_parquet(artifact.file("commands.parquet"))
    mocap = pd.read_parquet(artifact.file("mocap.parquet"))
    runs = pd.read_parquet(artifact.file("runs.parquet"))
    assert runs["run_id"].tolist() == ["sim-a", "sim-b"]
    assert runs["n_frames"].tolist() == [300, 150]  # as long as the recordings
    a = commands[commands["run_id"] == "sim-a"]
    np.testing.assert_allclose(a["t"], [0.0, 0.4, 1.2], atol=1e-9)  # the recorded times
    np.testing.assert_array_equal(a[["p_cmd_0", "p_cmd_1", "p_cmd_2"]].to_numpy(),
                                  [[2.0, 2.0, 2.0], [2.0, 2.0, 3.0], [-1.0, 2.0, 3.0]])
    assert (mocap.groupby("run_id").size() == [300, 150]).all()
    # keyed by the recordings' content: another folder with the same files, the same key
    copy = tmp_path / "copy"
    copy.mkdir()
    for path in data.iterdir():
        (copy / path.name).write_bytes(path.read_bytes())
    moved = make_cfg("robot=sim_sorolex_replay", f"robot.replay.data_dir={copy}",
                     "robot.replay.pattern=*.csv")
    assert key("collect", moved) == key("collect", cfg)
    (copy / "b.csv").write_text(HEADER + good_rows(160))
    assert key("collect", moved) != key("collect", cfg)
