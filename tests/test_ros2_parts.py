"""Parts of the ROS 2 path that need no ROS: install hint, gate, chunks, field paths, twin physics."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pipeline.arm import sim_arm
from pipeline.chain import CHAIN, STAGES
from pipeline.data.ros_messages import read_pressures, read_stamp_ns, set_field, write_stamp_ns
from pipeline.infra.artifacts import ArtifactStore
from pipeline.keys import key
from pipeline.ros2.collector import collect_ros2
from pipeline.ros2.gate import CommandGate
from pipeline.ros2.node import RosUnavailableError
from pipeline.ros2.recorder import ChunkedRecorder
from pipeline.ros2.twin import ArmSimulator
from pipeline.schemas import Stage
from pipeline.stages.collect import STAGE, _set_aside_incomplete
from pipeline.stages.twin import twin


def test_without_rclpy_ros2_and_twin_fail_with_the_install_hint(monkeypatch, make_cfg,
                                                                tmp_path):
    monkeypatch.setitem(sys.modules, "rclpy", None)  # import rclpy -> ImportError
    cfg = make_cfg("robot=ros2")
    robot, exploration = OmegaConf.to_object(cfg.robot), OmegaConf.to_object(cfg.exploration)
    for attempt in (lambda: collect_ros2(robot, exploration, tmp_path, {}), lambda: twin(cfg)):
        with pytest.raises(RosUnavailableError) as err:
            attempt()
        message = str(err.value)
        assert "pip install -e .[ros]" in message and "make setup-ros" in message
        assert "\n" not in message


def test_twin_is_a_stage_but_not_part_of_all():
    assert Stage.twin in STAGES and Stage.twin not in CHAIN
    assert Stage.guard in STAGES and Stage.guard not in CHAIN
    assert CHAIN[0] is Stage.collect and CHAIN[-1] is Stage.evaluate


def test_gate_projects_then_checks_in_float64():
    limits = SimpleNamespace(p_min=0.0, p_max=6.9, sum_max=13.0, preload=2.0)
    gate = CommandGate(limits, 3)
    np.testing.assert_array_equal(gate.preload, [2.0, 2.0, 2.0])
    at_bound = gate(np.array([50.0, 0.0, 0.0]))
    assert 6.9 - 1e-6 < at_bound[0] <= 6.9 and at_bound.dtype == np.float64  # not a float32
    crowded = gate(np.array([6.9, 6.9, 6.9]))
    assert crowded.sum() <= 13.0 and crowded.max() <= 6.9
    np.testing.assert_array_equal(gate(np.array([np.nan, 1.0, 1.0])), [0.0, 1.0, 1.0])
    with pytest.raises(ValueError, match=r"outside robot\.limits: \[0\.0, 6\.9\] per valve"):
        gate.check(np.array([7.0, 0.0, 0.0]))


def test_recorder_writes_chunks_and_reads_every_row_back(tmp_path):
    recorder = ChunkedRecorder(tmp_path / "chunks", {"test": True}, {"stage": "collect"})
    recorder.flush()  # nothing yet: no file
    assert not list((tmp_path / "chunks").iterdir())
    recorder.add_command("r0", 0.0, [2.0, 2.0, 2.0])
    recorder.add_frame("r0", 0.0, (0.1, 0.2, 0.3), True)
    recorder.flush()
    recorder.add_frame("r0", 0.01, (float("nan"),) * 3, False)
    recorder.add_command("r1", 0.0, [1.0, 2.0, 3.0])
    recorder.add_frame("r1", 0.0, (0.1, 0.2, 0.3), True)
    commands, mocap = recorder.read_all()
    assert sorted(p.name for p in (tmp_path / "chunks").iterdir()) == [
        "commands-00000.parquet", "commands-00001.parquet", "mocap-00000.parquet",
        "mocap-00001.parquet"]
    assert commands["run_id"].tolist() == ["r0", "r1"]
    assert mocap["t"].tolist() == [0.0, 0.01, 0.0] and mocap["valid"].tolist() == [True, False,
                                                                                  True]
    assert isinstance(commands, pd.DataFrame) and commands["p_cmd_2"].tolist() == [2.0, 3.0]


def test_field_paths_read_and_write_nested_messages():
    stamp = SimpleNamespace(sec=0, nanosec=0)
    message = SimpleNamespace(header=SimpleNamespace(stamp=stamp), data=[1.0, 2.0, 3.0])
    write_stamp_ns(message, "header.stamp", 12_345_000_000_007)
    assert (stamp.sec, stamp.nanosec) == (12_345, 7)
    assert read_stamp_ns(message, "header.stamp") == 12_345_000_000_007
    np.testing.assert_array_equal(read_pressures(message, "data", 3), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="holds 3 values, expected 4"):
        read_pressures(message, "data", 4)
    with pytest.raises(ValueError, match=r"no field 'header.stemp'"):
        read_stamp_ns(message, "header.stemp")
    with pytest.raises(ValueError, match="no field 'p_d'"):
        set_field(message, "p_d", [0.0])


def test_twin_simulator_follows_the_simulated_arm(make_cfg):
    cfg = make_cfg("robot=ros2", "robot.twin.mocap.noise_std_m=0", "robot.twin.mocap.drop_prob=0",
                   "robot.twin.mocap.burst_prob=0")
    simulator = ArmSimulator(cfg.robot.twin, 2.0, 3)
    commands = np.repeat([[2.0, 2.0, 2.0], [5.0, 1.0, 1.0], [1.0, 4.0, 3.0]], [7, 30, 23], axis=0)
    params = sim_arm.SimParams.from_config(cfg.robot.twin)
    state = sim_arm.reset(params, jax.random.key(int(cfg.robot.twin.seed)), jnp.full(3, 2.0))
    step = jax.jit(lambda s, c: (sim_arm.tip_position(params, s), sim_arm.advance(params, s, c, 1)))
    positions = []
    for k, command in enumerate(commands):
        if k in (7, 37):  # mid-chunk: the frames computed ahead are recomputed
            simulator.set_command(command)
        position, _ = simulator.next_frame()
        expected, state = step(state, jnp.asarray(command, jnp.float32))
        np.testing.assert_allclose(position, expected, atol=1e-6, err_msg=f"frame {k}")
        positions.append(position)
    assert np.ptp(positions, axis=0).max() > 5e-3  # the commands moved it by millimetres


def test_collect_key_follows_what_is_recorded_not_how(make_cfg):
    first = key("collect", make_cfg("robot=ros2"))
    assert first == key("collect", make_cfg("robot=ros2", "robot.reuse_incomplete=true",
                                       "robot.domain_id=5", "robot.flush_every_s=1"))
    assert first != key("collect", make_cfg("robot=ros2", "robot.session=rehearsal"))
    assert first != key("collect", make_cfg("robot=ros2", "robot.time_scale=4"))


def test_incomplete_artifact_is_set_aside_unless_reused(tmp_path):
    store = ArtifactStore(tmp_path)
    with store.writing(STAGE, "k", {}) as writer:
        writer.summary = {"incomplete_runs": ["ros2-000"]}
    _set_aside_incomplete(store, "k", reuse=True)
    assert store.find(STAGE, "k") is not None
    _set_aside_incomplete(store, "k", reuse=False)
    assert store.find(STAGE, "k") is None
    (aside,) = (tmp_path / STAGE).glob("k.incomplete-*")
    assert (aside / "artifact.json").is_file()
