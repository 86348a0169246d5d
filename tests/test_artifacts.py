"""Artifact keys, reuse, force, and atomic writes (a killed stage leaves nothing readable)."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time

import pandas as pd
import pyarrow.parquet as pq
import pytest

from pipeline import keys
from pipeline.data.schemas import COMMANDS, DataError, read_table, write_table
from pipeline.infra.artifacts import ArtifactStore, MissingArtifactError, artifact_key, produce


def test_keys_follow_the_determining_config_only(make_cfg):
    base = make_cfg("experiment=quick")
    assert keys.key("collect", base) == keys.key("collect", make_cfg("experiment=quick"))
    # settings of later stages do not touch upstream keys: sweeps share upstream artifacts
    for later in ("seed=3", "agent=ppo_rnn", "model.hidden=16", "dataset.window=8"):
        other = make_cfg("experiment=quick", later)
        assert keys.key("collect", other) == keys.key("collect", base) and keys.key("align", other) == keys.key("align", base)
    # an align setting changes align only
    resampled = make_cfg("experiment=quick", "dataset.align.resample_hz=10")
    assert keys.key("collect", resampled) == keys.key("collect", base)
    assert keys.key("align", resampled) != keys.key("align", base)
    # an exploration setting changes both
    alpha = make_cfg("experiment=quick", "exploration.alpha=0.7")
    assert keys.key("collect", alpha) != keys.key("collect", base) and keys.key("align", alpha) != keys.key("align", base)
    # where the outputs go is not part of any key
    assert keys.key("collect", make_cfg("experiment=quick", "paths.output_dir=/elsewhere")) == \
        keys.key("collect", base)


def test_imported_data_is_keyed_by_content_not_location(make_cfg, sorolex_dir, tmp_path):
    copy = tmp_path / "copy"
    copy.mkdir()
    name = "Step_control_17_10_12_20.csv"
    (copy / name).write_bytes((sorolex_dir / name).read_bytes())
    here = make_cfg("robot=sorolex_csv", f"robot.data_dir={sorolex_dir}", f"robot.files=[{name}]")
    there = make_cfg("robot=sorolex_csv", f"robot.data_dir={copy}", f"robot.files=[{name}]")
    assert keys.key("collect", here) == keys.key("collect", there)
    os.utime(copy / name, (0, 0))  # a new modification time alone changes nothing
    assert keys.key("collect", there) == keys.key("collect", here)
    text = (sorolex_dir / name).read_text()
    (copy / name).write_text(text.replace("2.0,2.0,2.0", "2.0,2.0,2.1", 1))
    assert keys.key("collect", there) != keys.key("collect", here)


def build_table(writer):
    frame = pd.DataFrame({"run_id": "a", "t": [0.0, 0.5], "p_cmd_0": 2.0, "p_cmd_1": 2.0,
                          "p_cmd_2": 2.0})
    write_table(frame, writer.file("commands.parquet"), COMMANDS, {"k": 1})
    writer.summary = {"rows": 2}


def test_reuse_and_force(tmp_path, caplog):
    store = ArtifactStore(tmp_path)
    first = produce(store, "demo", {"a": 1}, {}, build_table)
    created = first.manifest["created"]
    inode = os.stat(first.file("commands.parquet")).st_ino
    with caplog.at_level(logging.INFO, logger="pipeline.infra.artifacts"):
        again = produce(store, "demo", {"a": 1}, {}, lambda w: pytest.fail("rebuilt"))
    assert again.path == first.path and "reusing" in caplog.text
    forced = produce(store, "demo", {"a": 1}, {}, build_table, force=True)
    assert forced.path == first.path
    assert os.stat(forced.file("commands.parquet")).st_ino != inode
    assert forced.manifest["created"] >= created
    assert produce(store, "demo", {"a": 2}, {}, build_table).key != first.key
    assert not [p for p in (tmp_path / "demo").iterdir() if p.name.startswith((".tmp", ".old"))]


def test_a_failing_build_leaves_no_artifact_and_keeps_the_old_one(tmp_path):
    store = ArtifactStore(tmp_path)

    def broken(writer):
        build_table(writer)
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        produce(store, "demo", {"a": 1}, {}, broken)
    assert list((tmp_path / "demo").glob("[!.]*")) == []
    with pytest.raises(MissingArtifactError, match="stage=demo"):
        store.require("demo", "0" * 12)
    good = produce(store, "demo", {"a": 1}, {}, build_table)
    with pytest.raises(RuntimeError):
        produce(store, "demo", {"a": 1}, {}, broken, force=True)
    assert read_table(good.file("commands.parquet"), COMMANDS)[0].shape == (2, 5)


KILLED_WRITER = textwrap.dedent("""
    import sys, time, pathlib
    import pandas as pd
    from pipeline.infra.artifacts import ArtifactStore, produce
    from pipeline.data.schemas import COMMANDS, write_table

    def slow(writer):
        frame = pd.DataFrame({"run_id": "a", "t": [0.0], "p_cmd_0": 2.0, "p_cmd_1": 2.0,
                              "p_cmd_2": 2.0})
        write_table(frame, writer.file("commands.parquet"), COMMANDS)
        pathlib.Path(sys.argv[2]).touch()  # tell the test we are mid-write
        time.sleep(60)

    produce(ArtifactStore(sys.argv[1]), "demo", {"a": 1}, {}, slow)
""")


def test_a_stage_killed_mid_write_leaves_nothing_a_later_stage_reads(tmp_path):
    marker = tmp_path / "mid-write"
    proc = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(tmp_path / "store"),
                             str(marker)])
    try:
        deadline = time.time() + 60
        while not marker.exists():
            assert proc.poll() is None and time.time() < deadline, "writer never got going"
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    store = ArtifactStore(tmp_path / "store")
    leftovers = list((tmp_path / "store" / "demo").iterdir())
    assert all(p.name.startswith(".") for p in leftovers)  # only hidden temporaries and locks
    key = artifact_key({"a": 1}, {})
    assert store.find("demo", key) is None
    rebuilt = produce(store, "demo", {"a": 1}, {}, build_table)  # the lock died with the process
    assert rebuilt.manifest["summary"] == {"rows": 2}


def test_parquet_files_carry_units_and_config(tmp_path):
    path = tmp_path / "c.parquet"
    frame = pd.DataFrame({"run_id": "a", "t": [0.0], "p_cmd_0": 2.0, "p_cmd_1": 2.0,
                          "p_cmd_2": 2.0})
    write_table(frame, path, COMMANDS, {"exploration": {"alpha": 0.5}}, {"stage": "collect"})
    schema = pq.read_schema(path)
    meta = json.loads(schema.metadata[b"sorolearn"])
    assert meta["units"]["p_cmd_0"] == "kPa" and meta["units"]["t"] == "s"
    assert meta["config"]["exploration"]["alpha"] == 0.5
    assert schema.field("p_cmd_1").metadata[b"unit"] == b"kPa"


def test_reading_the_wrong_table_or_a_corrupt_file_is_a_clear_error(tmp_path):
    path = tmp_path / "c.parquet"
    frame = pd.DataFrame({"run_id": "a", "t": [0.0], "p_cmd_0": 2.0, "p_cmd_1": 2.0,
                          "p_cmd_2": 2.0})
    write_table(frame, path, COMMANDS)
    from pipeline.data.schemas import MOCAP

    with pytest.raises(DataError, match="holds a 'commands' table, expected 'mocap'"):
        read_table(path, MOCAP)
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(DataError, match="not a readable Parquet file"):
        read_table(path, COMMANDS)
