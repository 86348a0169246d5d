"""``stage=twin``: the simulated arm as a ROS 2 node, a stand-in for the real arm.

It listens to the valve commands on ``robot.command_topic`` and publishes the marker pose on
``robot.pose_topic`` (``robot.pose_type``, stamped, frame ``robot.twin.frame_id``) at
``robot.twin.mocap.rate_hz`` of the arm's time, with the mocap noise, timestamp jitter and dropped
frames of ``pipeline/arm/sim_arm.py`` (a dropped frame is simply not published, as a mocap driver
does). With ``robot.time_scale`` > 1 the arm's time runs that much faster than the wall clock
(collect must use the same value), so a rehearsal or a test of the ROS 2 path takes seconds.

Frames are due on a fixed schedule; when the process falls behind it publishes the late frames at
once, each with its nominal stamp (like a camera clock), shifted by ``robot.twin.clock_offset_s``
(a motion capture clock apart from the stages', default 0). Commands take effect at the next frame;
a command outside ``robot.limits`` or the arm's ``robot.rating`` is logged as an error, counted
(the stage then fails at the end) and applied as the valves would: saturated onto the safe set.
Deadman (:class:`pipeline.ros2.guard.Deadman`, as the guard node): when no command arrived within
``robot.command_timeout_s`` of the last one, the arm returns to the rating's preload.

Like the guard, it answers for the arm (:mod:`pipeline.ros2.handshake`, role ``twin``) and
accepts exactly one publisher of commands: once a second appears, the arm returns to the preload
and stays there (the stage fails at the end).

It runs on its own ROS domain, ``robot.rehearsal_domain_id`` (never ``robot.domain_id``): a
rehearsal's stages follow it there only with ``robot.rehearsal=true``, so a rehearsal on a lab
network cannot reach the real arm, and the twin's poses cannot feed a real arm's watchdog.

Runs until SIGINT/SIGTERM or ``robot.twin.max_duration_s`` (wall). With ``robot.twin.record_path``
every command received is appended to a JSON-lines file (receipt time in ROS ns, pressures in
kPa, whether within the limits), flushed line by line so that it survives a kill; a return to
the preload by the deadman is a line with ``"deadman": true``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from pathlib import Path
from typing import IO, Any

import jax
import jax.numpy as jnp
import numpy as np

from pipeline.arm import sim_arm
from pipeline.arm.limits import UnsafeCommandError, validate_limits
from pipeline.data.ros_messages import (
    NS_PER_S,
    message_class,
    read_pressures,
    write_position,
    write_stamp_ns,
)
from pipeline.ros2.gate import CommandGate
from pipeline.ros2.guard import Deadman, SinglePublisher, rating_preload
from pipeline.ros2.handshake import HandshakeAnswer
from pipeline.ros2.node import StopSignals, qos_profile, require_rclpy, ros_node
from pipeline.schemas import RobotConfig, RobotKind, Ros2RobotConfig, TwinConfig

log = logging.getLogger(__name__)
NODE_NAME = "sorolearn_twin"
_SPIN_SLICE_S = 0.005  # wall: longest wait inside the executor
_CHUNK = 16  # frames simulated per JAX call
_SPIN_EVERY_S = 0.005  # wall: while catching up on late frames, still take commands this often


class ArmSimulator:
    """The simulated arm stepped one mocap frame at a time, seen through an imperfect mocap.

    Frames are computed ``_CHUNK`` at a time under the command in force (one JAX call per chunk
    instead of per frame: the call overhead, not the physics, is the cost); a new command drops
    the frames not yet taken and the next chunk starts from the state it arrived at.
    """

    def __init__(self, twin: TwinConfig, preload: float, n_valves: int):
        session_key = jax.random.key(int(twin.seed))
        # this session's physics (the nominal ones unless physics.session_std spreads them)
        self.params = params = sim_arm.session_params(
            sim_arm.SimParams.from_config(twin), jax.random.fold_in(session_key, 1))
        # plain floats: reading a config node per frame would cost more than the frame itself
        mocap = twin.mocap
        self._period_s = 1.0 / float(mocap.rate_hz)
        self._noise_std_m, self._jitter_std_s = float(mocap.noise_std_m), float(mocap.jitter_std_s)
        self._drop_prob, self._burst_prob = float(mocap.drop_prob), float(mocap.burst_prob)
        self._burst_len = int(mocap.burst_len)
        self._command = jnp.full((n_valves,), float(preload), jnp.float32)
        self._state = sim_arm.reset(params, session_key, self._command)
        self._rng = np.random.default_rng(int(twin.seed))
        self._burst_left = 0

        @jax.jit
        def chunk(state, command):
            def frame(state, _):
                next_state = sim_arm.advance(params, state, command, 1)
                return next_state, (sim_arm.tip_position(params, state), next_state)

            _, (positions, states) = jax.lax.scan(frame, state, None, length=_CHUNK)
            return positions, states

        self._chunk = chunk
        self._positions: np.ndarray | None = None  # [_CHUNK, 3] m, frames computed ahead
        self._states: Any = None  # the state after each of those frames
        self._taken = 0
        self._plan()  # compiles before serving

    def _plan(self) -> None:
        positions, states = jax.device_get(self._chunk(self._state, self._command))
        self._positions = np.asarray(positions, np.float64)
        self._states, self._taken = states, 0

    def _rebase(self) -> None:
        """Make the state after the last frame taken the start of the next chunk."""
        if self._taken:
            self._state = jax.tree_util.tree_map(lambda x: x[self._taken - 1], self._states)
        self._positions, self._taken = None, 0

    def set_command(self, command: np.ndarray) -> None:
        """Valve command [kPa] in force from the next frame on."""
        self._rebase()
        self._command = jnp.asarray(command, jnp.float32)

    def next_frame(self) -> tuple[np.ndarray | None, float]:
        """This frame's position as the mocap reports it [m] (None: dropped) and its stamp jitter
        [s]; the arm then advances one frame period under the command in force."""
        if self._positions is None or self._taken == _CHUNK:
            self._rebase()
            self._plan()
        position = self._positions[self._taken]
        self._taken += 1
        rng, bound = self._rng, 0.4 * self._period_s
        jitter = min(max(rng.normal() * self._jitter_std_s, -bound), bound)
        if rng.random() < self._burst_prob:
            self._burst_left = self._burst_len
        dropped = rng.random() < self._drop_prob or self._burst_left > 0
        self._burst_left = max(self._burst_left - 1, 0)
        if dropped:
            return None, jitter
        return position + rng.normal(0.0, self._noise_std_m, 3), jitter


class TwinNode:
    """Publishes the simulator's poses on schedule; applies the commands it receives."""

    def __init__(self, node: Any, executor: Any, robot: Ros2RobotConfig, simulator: ArmSimulator,
                 record: IO[str] | None):
        self._node, self._executor, self._robot = node, executor, robot
        self._simulator, self._record = simulator, record
        self._stamp_field, self._position_field = robot.stamp_field, robot.position_field
        self._frame_id = str(robot.twin.frame_id)
        self._gate = CommandGate.for_robot(robot)
        self._preload = rating_preload(robot)
        self.deadman = Deadman(float(robot.command_timeout_s) / float(robot.time_scale))
        self._at_preload = True  # the simulated arm starts at rest
        self._pose_type = message_class(robot.pose_type)
        self._publisher = node.create_publisher(self._pose_type, robot.pose_topic,
                                                qos_profile(robot.pose_qos))
        node.create_subscription(message_class(robot.command_type), robot.command_topic,
                                 self._on_command, qos_profile(robot.command_qos))
        self.single = SinglePublisher(node, robot.command_topic)
        self.handshake = HandshakeAnswer(node, robot, "twin")
        self.frames_published = 0
        self.frames_dropped = 0
        self.commands_received = 0
        self.commands_outside_limits = 0
        self.deadman_returns = 0

    def _now_ns(self) -> int:
        return self._node.get_clock().now().nanoseconds

    def _refusing(self, now: float, force: bool = False) -> bool:
        latched = self.single.refusal is not None
        refusal = self.single.check(now, force)
        if refusal is not None and not latched:
            log.error("twin: %s", refusal)
            self._simulator.set_command(self._preload)
            self._at_preload = True
            self._write({"receipt_ns": self._now_ns(), "pressures": self._preload.tolist(),
                         "within_limits": True, "refused": refusal})
        return refusal is not None

    def _on_command(self, message: Any) -> None:
        receipt = self._now_ns()
        if self._refusing(time.monotonic(), force=True):
            self._write({"receipt_ns": receipt, "ignored": True,
                         "pressures": np.asarray(getattr(message, "data", []), float).tolist()})
            return
        self.deadman.feed(time.monotonic())
        pressures = read_pressures(message, self._robot.command_field, self._robot.n_valves)
        self.commands_received += 1
        try:
            self._gate.check(pressures)
            within = True
        except ValueError as err:
            within = False
            self.commands_outside_limits += 1
            log.error("twin: received an unsafe command: %s", err)
        applied = self._gate(pressures)
        self._simulator.set_command(applied)
        self._at_preload = bool(np.array_equal(applied, self._preload))
        self._write({"receipt_ns": receipt, "pressures": pressures.tolist(),
                     "within_limits": within})

    def _write(self, row: dict[str, Any]) -> None:
        if self._record is not None:
            self._record.write(json.dumps(row) + "\n")
            self._record.flush()

    def _check_deadman(self, now: float) -> None:
        """Back to the preload once no command arrived within robot.command_timeout_s."""
        if self._at_preload or not self.deadman.stale(now):
            return
        self._simulator.set_command(self._preload)
        self._at_preload = True
        self.deadman_returns += 1
        log.warning("twin: no command on %s for robot.command_timeout_s=%s s: back to the "
                    "preload %s kPa", self._robot.command_topic, self._robot.command_timeout_s,
                    self._preload.tolist())
        self._write({"receipt_ns": self._now_ns(), "pressures": self._preload.tolist(),
                     "within_limits": True, "deadman": True})

    def _publish(self, stamp_ns: int, position: np.ndarray) -> None:
        message = self._pose_type()
        if self._stamp_field:
            write_stamp_ns(message, self._stamp_field, stamp_ns)
        header = getattr(message, "header", None)
        if header is not None:
            header.frame_id = self._frame_id
        write_position(message, self._position_field, position)
        self._publisher.publish(message)

    def serve(self, signals: StopSignals) -> str:
        """Publish frames until a stop signal or ``twin.max_duration_s``; return why it ended."""
        robot = self._robot
        scale = float(robot.time_scale)
        period_s = 1.0 / float(robot.twin.mocap.rate_hz)  # arm seconds
        period_wall_s = period_s / scale
        max_wall_s = robot.twin.max_duration_s
        offset_ns = round(float(robot.twin.clock_offset_s) * NS_PER_S)  # a mocap clock apart
        start, start_ns = time.monotonic(), self._now_ns() + offset_ns
        frame, spun = 0, start
        while not signals.received:
            now = time.monotonic()
            if max_wall_s is not None and now - start > float(max_wall_s):
                return f"robot.twin.max_duration_s={max_wall_s} s elapsed"
            if not self._refusing(now):
                self._check_deadman(now)
            due = start + frame * period_wall_s
            if now < due or now - spun > _SPIN_EVERY_S:
                self._executor.spin_once(timeout_sec=min(max(due - now, 0.0), _SPIN_SLICE_S))
                spun = time.monotonic()
                continue
            position, jitter = self._simulator.next_frame()
            if position is None:
                self.frames_dropped += 1
            else:
                stamp = start_ns + round((frame * period_s + jitter) / scale * NS_PER_S)
                self._publish(stamp, position)
                self.frames_published += 1
            frame += 1
        return f"{signals.received} received"


def serve(robot: RobotConfig) -> None:
    """Serve the digital twin on ``robot``'s topics (``robot=ros2``) until stopped."""
    if RobotKind(robot.kind) is not RobotKind.ros2:
        raise ValueError(f"stage=twin serves the topics of a ROS 2 robot; got robot={robot.name} "
                         f"(add robot=ros2 and the same robot.* overrides as the collect)")
    if not float(robot.time_scale) > 0:
        raise ValueError(f"robot.time_scale={robot.time_scale} must be positive")
    require_rclpy()
    validate_limits(robot.limits, robot.n_valves)
    simulator = ArmSimulator(robot.twin, float(robot.limits.preload), robot.n_valves)
    record_path = Path(robot.twin.record_path) if robot.twin.record_path else None
    if record_path is not None:
        record_path.parent.mkdir(parents=True, exist_ok=True)
    with (StopSignals() as signals,
          ros_node(NODE_NAME, int(robot.rehearsal_domain_id)) as (node, executor),
          open(record_path, "w") if record_path else contextlib.nullcontext() as record):
        node_ = TwinNode(node, executor, robot, simulator, record)
        log.info("twin: simulated arm on %s at %g Hz (time_scale %g), listening on %s, on "
                 "ROS domain robot.rehearsal_domain_id=%s (stages join it with "
                 "robot.rehearsal=true)", robot.pose_topic, float(robot.twin.mocap.rate_hz),
                 float(robot.time_scale), robot.command_topic, robot.rehearsal_domain_id)
        reason = node_.serve(signals)
    log.info("twin: stopped (%s): %d frames published, %d dropped by the simulated mocap, "
             "%d commands received", reason, node_.frames_published, node_.frames_dropped,
             node_.commands_received)
    if node_.deadman_returns:
        log.info("twin: the deadman returned the arm to the preload %d time(s)",
                 node_.deadman_returns)
    if node_.single.refusal is not None:
        raise UnsafeCommandError(f"twin: {node_.single.refusal}")
    if node_.commands_outside_limits:
        raise UnsafeCommandError(f"twin: {node_.commands_outside_limits} of the "
                                 f"{node_.commands_received} commands received were outside "
                                 f"robot.limits or the arm's rating robot.rating")

