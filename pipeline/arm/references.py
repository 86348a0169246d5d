"""Reference paths for the arm's marker to follow: one representation for training, evaluation
and control.

A :class:`Reference` is a pytree evaluated by :func:`position` ``(reference, t [s]) -> [3] m``, a
pure function that runs inside ``jit`` and ``vmap`` (the environment samples it every control
period). It holds either

- a closed **shape** in a plane through ``centre``: with ``theta = omega * t + phase``,
  ``centre + axis_a * cos(theta) + axis_b * sin(harmonic * theta)``; a circle (``|axis_a| =
  |axis_b|``, ``harmonic`` 1), an ellipse (other lengths) or a figure-eight (a 1:2 Lissajous,
  ``harmonic`` 2: it crosses itself at the centre); the sign of ``omega`` is the direction; a
  static goal is a shape of zero size; or
- a **table** of timed points (segments through waypoints, a timed CSV, a replayed measured path),
  followed by linear interpolation and held at its last point after its end.

Parameters are given in mm and s (:class:`ShapeSettings`, :func:`waypoints`, :func:`read_csv`,
:func:`replay`; :class:`ReplaySettings` and :func:`replay_stretches` for stretches of recorded
paths) and held in m and s; :func:`reference_settings` reads either kind from the config.
:func:`draw` draws random shapes for training, inside jit; :func:`check_reachable` refuses a
reference that leaves a set of reachable positions before anything moves.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from flax import struct

from pipeline.schemas import ConfigError, ReferenceConfig

MM_PER_M = 1000.0
SHAPES = ("circle", "ellipse", "figure_eight")
REPLAY = "replay"  # the kind of a replayed measured path (:class:`ReplaySettings`)
_CHUNK = 256  # points measured against the reachable set at once (check_points: memory)
# the axes of each plane a shape can lie in (x, y, z: 0, 1, 2 of the mocap frame)
PLANES = {"xz": (0, 2), "xy": (0, 1), "yz": (1, 2)}
# the plane of the random draws: the arms' workspace is a surface in x and z of the mocap frame
# (y spans a few mm where x and z span tens, on the simulated arm and in the paper's recordings)
DRAW_PLANE = "xz"
# a table every reference carries, so that shapes and tables stack into one batch
_EMPTY_TABLE = 2


class InvalidReference(ConfigError):
    """A reference that cannot be followed: malformed, or leaving the reachable set."""


@struct.dataclass
class Reference:
    """A reference path (a pytree: stack and vmap it; see the module docstring).

    centre: [3] m, the shape's centre.
    axis_a, axis_b: [3] m, the shape's two in-plane axes, each as long as its semi-axis.
    omega: rad/s, the shape's angular rate (its sign the direction; 0: static).
    phase: rad, the shape's angle at t = 0.
    harmonic: the multiple of the angle on ``axis_b`` (1: circle, ellipse; 2: figure-eight).
    times: [K] s, increasing, the table's times.
    points: [K, 3] m, the table's points.
    tabulated: bool scalar, True: the table is the path, False: the shape is.
    """

    centre: jax.Array
    axis_a: jax.Array
    axis_b: jax.Array
    omega: jax.Array
    phase: jax.Array
    harmonic: jax.Array
    times: jax.Array
    points: jax.Array
    tabulated: jax.Array


def position(reference: Reference, t: jax.Array) -> jax.Array:
    """``[3]`` m: where ``reference`` is at ``t`` s (a scalar; vmap for many)."""
    theta = reference.omega * t + reference.phase
    shape = (reference.centre + reference.axis_a * jnp.cos(theta)
             + reference.axis_b * jnp.sin(reference.harmonic * theta))
    table = jax.vmap(jnp.interp, in_axes=(None, None, 1))(t, reference.times, reference.points)
    return jnp.where(reference.tabulated, table, shape)


def positions(reference: Reference, times: jax.Array) -> jax.Array:
    """``[T, 3]`` m: :func:`position` at each of ``times [T]`` s."""
    return jax.vmap(position, in_axes=(None, 0))(reference, jnp.asarray(times, jnp.float32))


def static(goal_m: jax.Array) -> Reference:
    """A reference that stays at ``goal_m [3]`` m (a shape of zero size)."""
    goal = jnp.asarray(goal_m, jnp.float32)
    chex.assert_shape(goal, (3,))
    zero = jnp.zeros(3, jnp.float32)
    return _shape(goal, zero, zero, 0.0, 0.0, 1.0)


def _shape(centre, axis_a, axis_b, omega, phase, harmonic) -> Reference:
    f32 = lambda value: jnp.asarray(value, jnp.float32)  # noqa: E731
    return Reference(f32(centre), f32(axis_a), f32(axis_b), f32(omega), f32(phase),
                     f32(harmonic), jnp.arange(_EMPTY_TABLE, dtype=jnp.float32),
                     jnp.zeros((_EMPTY_TABLE, 3), jnp.float32), jnp.asarray(False))


@dataclass(frozen=True)
class ShapeSettings:
    """A closed shape, in mm and s.

    kind: circle | ellipse | figure_eight.
    centre_mm: [3] mm, in the mocap frame.
    size_mm: the radius (circle), or the semi-axis along the plane's first axis.
    size_b_mm: the semi-axis along the plane's second axis (ellipse, figure-eight: the half
      height of each loop); None: ``size_mm``.
    period_s: s per lap.
    phase_deg: the shape's angle at t = 0 (0: at ``centre + size`` along the plane's first axis).
    direction: +1 counter-clockwise in the plane's axes (first toward second), -1 clockwise.
    plane: xz | xy | yz.
    """

    kind: str = "circle"
    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    size_mm: float = 5.0
    size_b_mm: float | None = None
    period_s: float = 20.0
    phase_deg: float = 0.0
    direction: int = 1
    plane: str = "xz"


def shape(settings: ShapeSettings) -> Reference:
    """The :class:`Reference` of a closed shape; a bad setting raises :class:`InvalidReference`
    naming it."""
    if settings.kind not in SHAPES:
        raise InvalidReference(f"reference kind {settings.kind!r}: expected one of "
                               f"{(*SHAPES, REPLAY)}")
    if settings.plane not in PLANES:
        raise InvalidReference(f"reference plane {settings.plane!r}: expected one of "
                             f"{tuple(PLANES)}")
    if settings.direction not in (1, -1):
        raise InvalidReference(f"reference direction {settings.direction}: expected 1 "
                             f"(counter-clockwise) or -1 (clockwise)")
    size_b = settings.size_mm if settings.size_b_mm is None else settings.size_b_mm
    values = {"size_mm": settings.size_mm, "size_b_mm": size_b, "period_s": settings.period_s}
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0):
            raise InvalidReference(f"reference {name}={value}: expected a finite number > 0")
    centre = np.asarray(settings.centre_mm, np.float64)
    if centre.shape != (3,) or not np.isfinite(centre).all():
        raise InvalidReference(f"reference centre_mm={list(settings.centre_mm)}: expected finite "
                             f"[x, y, z] mm")
    first, second = PLANES[settings.plane]
    axis_a, axis_b = np.zeros(3), np.zeros(3)
    axis_a[first] = settings.size_mm / MM_PER_M
    axis_b[second] = size_b / MM_PER_M
    harmonic = 2.0 if settings.kind == "figure_eight" else 1.0
    omega = settings.direction * 2.0 * math.pi / settings.period_s
    return _shape(centre / MM_PER_M, axis_a, axis_b, omega, math.radians(settings.phase_deg),
                  harmonic)


def table(times_s: np.ndarray, points_m: np.ndarray, what: str = "reference") -> Reference:
    """A :class:`Reference` through ``points_m [K, 3]`` m at ``times_s [K]`` s (finite, strictly
    increasing), held at the last point after it; errors name ``what``."""
    times = np.asarray(times_s, np.float64)
    points = np.asarray(points_m, np.float64)
    if times.ndim != 1 or points.shape != (len(times), 3) or len(times) < 1:
        raise InvalidReference(f"{what}: expected times [K] and points [K, 3], got "
                             f"{times.shape} and {points.shape}")
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1) | ~np.isfinite(times))
    if len(bad):
        raise InvalidReference(f"{what}: row {bad[0]} is not finite (t={times[bad[0]]}, "
                             f"point={points[bad[0]].tolist()})")
    steps = np.flatnonzero(np.diff(times) <= 0)
    if len(steps):
        row = steps[0] + 1
        raise InvalidReference(f"{what}: times must increase; row {row} has t={times[row]:g} s "
                             f"after t={times[row - 1]:g} s")
    if len(times) == 1:  # one point: held from the start
        times, points = np.array([times[0], times[0] + 1.0]), np.repeat(points, 2, axis=0)
    zero = jnp.zeros(3, jnp.float32)
    return Reference(zero, zero, zero, jnp.float32(0.0), jnp.float32(0.0), jnp.float32(1.0),
                     jnp.asarray(times, jnp.float32), jnp.asarray(points, jnp.float32),
                     jnp.asarray(True))


def waypoints(points_mm: np.ndarray, speed_mm_s: float, start_s: float = 0.0) -> Reference:
    """Straight segments through ``points_mm [N, 3]`` mm at ``speed_mm_s`` mm/s, from the first
    point at ``start_s`` s (a repeated point: a segment of zero length, skipped)."""
    points = np.asarray(points_mm, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise InvalidReference(f"reference waypoints: expected finite [x, y, z] rows in mm, got "
                             f"{points.tolist()}")
    if not (math.isfinite(speed_mm_s) and speed_mm_s > 0):
        raise InvalidReference(f"reference speed_mm_s={speed_mm_s}: expected a finite number > 0")
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], lengths > 0])
    times = start_s + np.concatenate([[0.0], np.cumsum(lengths[lengths > 0])]) / speed_mm_s
    return table(times, points[keep] / MM_PER_M, "reference waypoints")


# a CSV whose coordinates all lie within this many mm of the origin is taken for metres
_METRES_BELOW_MM = 2.0


def read_timed_points(path: Path, what: str, error: type[Exception]) -> np.ndarray:
    """The ``t,x,y,z`` columns (s, mm; further columns ignored) of a CSV as numbers ``[N, 4]``;
    one ``error`` naming ``what`` (e.g. the file and the setting it came from) for a file that
    cannot be read, a missing column, no row or an entry that is not a number. The callers check
    what their points must be (finite, increasing times, in mm)."""
    try:
        frame = pd.read_csv(path)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError) as err:
        raise error(f"{what}: cannot read it: {err}") from err
    missing = [c for c in ("t", "x", "y", "z") if c not in frame.columns]
    if missing:
        raise error(f"{what}: missing column(s) {missing}; expected t,x,y,z (s, mm), found "
                    f"{list(frame.columns)}")
    if frame.empty:
        raise error(f"{what}: no rows; expected t,x,y,z (s, mm)")
    try:
        return frame[["t", "x", "y", "z"]].to_numpy(np.float64)
    except (TypeError, ValueError) as err:
        raise error(f"{what}: t,x,y,z must be numbers: {err}") from err


def read_csv(path: Path) -> Reference:
    """The timed reference of a CSV with columns ``t,x,y,z`` (s, mm; further columns ignored).

    One clear :class:`InvalidReference` naming the file for a file that cannot be read, a missing
    column, a row that is not finite, times that do not increase, or coordinates that look like
    metres (every one within 2 mm of the origin of the mocap frame, where the arm never is).
    """
    path = Path(path)
    values = read_timed_points(path, f"reference CSV {path}", InvalidReference)
    points_mm = values[:, 1:]
    finite = np.isfinite(points_mm)
    if finite.all() and np.abs(points_mm).max() < _METRES_BELOW_MM:
        raise InvalidReference(
            f"reference CSV {path}: x, y, z look like metres (all within "
            f"{_METRES_BELOW_MM:g} mm of the origin, largest {np.abs(points_mm).max():g}); "
            f"expected mm")
    return table(values[:, 0], points_mm / MM_PER_M, f"reference CSV {path}")


def replay(times_s: np.ndarray, points_m: np.ndarray, slow_down: float = 1.0,
           what: str = "replayed reference") -> Reference:
    """A measured path replayed: ``points_m [T, 3]`` m measured at ``times_s [T]`` s (increasing),
    played ``slow_down`` times slower from t = 0 (the path the arm went through: reachable by
    construction)."""
    _check_slow_down(slow_down, what)
    times = np.asarray(times_s, np.float64)
    return table((times - times[:1]) * float(slow_down), points_m, what)


def _check_slow_down(slow_down: float, what: str) -> None:
    if not (math.isfinite(slow_down) and slow_down > 0):
        raise InvalidReference(f"{what}: slow_down={slow_down}: expected a finite number > 0")


@dataclass(frozen=True)
class ReplaySettings:
    """Stretches of measured paths, replayed (:func:`replay_stretches`).

    run: the recording to replay, by name; None: every recording given.
    file: a CSV ``t,x,y,z`` (s, mm) of a measured path, replayed instead of the recordings.
    slow_down: how many times slower than recorded.
    start_s: s into each path where its stretches may begin.
    """

    run: str | None = None
    file: str | None = None
    slow_down: float = 4.0
    start_s: float = 0.0


def replay_stretches(paths: Mapping[str, tuple[np.ndarray, np.ndarray]],
                     settings: ReplaySettings, seconds: float, count: int,
                     what: str = "replayed reference") -> list[Reference]:
    """``count`` stretches of the measured ``paths`` (by name: ``(times [T] s, points [T, 3]
    m)``), each followed for ``seconds`` s, ``seconds / slow_down`` s of the path played
    ``settings.slow_down`` times slower (:func:`replay`). The stretches begin at samples spread
    evenly over every sample from ``settings.start_s`` s into each path (``settings.run``: that
    path only) that leaves a whole stretch before the path's end: ``count`` 1 is the stretch from
    ``start_s`` on of the first path. A :class:`InvalidReference` naming ``what`` where the run
    is unknown or no path is long enough."""
    paths = _replayed(paths, settings, what)
    span = float(seconds) / float(settings.slow_down)  # s of the path in a stretch
    begins = []  # (name, sample) of every stretch that fits
    for name, (times, _) in paths.items():
        elapsed = np.asarray(times, np.float64) - float(times[0])
        fits = (elapsed >= settings.start_s - 1e-9) & (elapsed <= elapsed[-1] - span + 1e-9)
        begins.extend((name, int(sample)) for sample in np.flatnonzero(fits))
    if not begins:
        longest = max((float(times[-1] - times[0]) for times, _ in paths.values()), default=0.0)
        raise InvalidReference(
            f"{what}: no recording holds {span:g} s of path after start_s={settings.start_s:g} s "
            f"({seconds:g} s followed at slow_down={settings.slow_down:g}); the longest lasts "
            f"{longest:.1f} s")
    stretches = []
    for index in np.linspace(0, len(begins), count, endpoint=False).astype(int):
        name, first = begins[index]
        times, points = (np.asarray(a, np.float64) for a in paths[name])
        last = min(int(np.searchsorted(times, times[first] + span - 1e-9)), len(times) - 1)
        stretches.append(replay(times[first:last + 1], points[first:last + 1],
                                settings.slow_down,
                                f"{what} ({name} from {times[first] - times[0]:.1f} s)"))
    return stretches


def replay_rest(paths: Mapping[str, tuple[np.ndarray, np.ndarray]], settings: ReplaySettings,
                what: str = "replayed reference") -> tuple[str, Reference]:
    """``(name, reference)``: the measured path ``settings.run`` of ``paths`` (by name: ``(times
    [T] s, points [T, 3] m)``; None: the first) from ``settings.start_s`` s to its end, played
    ``settings.slow_down`` times slower (:func:`replay`); a :class:`InvalidReference` naming
    ``what`` where the run is unknown or ends before ``start_s``."""
    name, (times, points) = next(iter(_replayed(paths, settings, what).items()))
    times, points = np.asarray(times, np.float64), np.asarray(points, np.float64)
    kept = times - times[0] >= settings.start_s - 1e-9
    if kept.sum() < 2:
        raise InvalidReference(f"{what}: {name} lasts {times[-1] - times[0]:.1f} s, nothing to "
                               f"replay after start_s={settings.start_s:g} s")
    return name, replay(times[kept], points[kept], settings.slow_down,
                        f"{what} ({name} from {settings.start_s:g} s)")


def _replayed(paths: Mapping[str, tuple[np.ndarray, np.ndarray]], settings: ReplaySettings,
              what: str) -> Mapping[str, tuple[np.ndarray, np.ndarray]]:
    """The paths ``settings`` replays (its run's, or all), its numbers checked."""
    _check_slow_down(settings.slow_down, what)
    if not (math.isfinite(settings.start_s) and settings.start_s >= 0):
        raise InvalidReference(f"{what}: start_s={settings.start_s}: expected a finite number "
                               f">= 0 s")
    if not paths:
        raise InvalidReference(f"{what}: no measured path to replay")
    if settings.run is None:
        return paths
    if settings.run not in paths:
        raise InvalidReference(f"{what}: run {settings.run!r} is not among the recordings "
                               f"{sorted(paths)}")
    return {settings.run: paths[settings.run]}


def measured_paths(settings: ReplaySettings,
                   recorded: Mapping[str, tuple[np.ndarray, np.ndarray]], what: str
                   ) -> Mapping[str, tuple[np.ndarray, np.ndarray]]:
    """The measured paths ``settings`` replays, by name (``(times [T] s, points [T, 3] m)``): its
    CSV's (:func:`csv_path`), or ``recorded``, the recordings the goals come from; a
    :class:`InvalidReference` naming ``what`` where there are neither."""
    if settings.file is not None:
        return {str(settings.file): csv_path(Path(settings.file))}
    if not recorded:
        raise InvalidReference(
            f"{what}: a replayed path needs the recordings the goals come from (env=learned on "
            f"recorded or collected runs) or a CSV of one (file: t,x,y,z in s and mm)")
    return recorded


def csv_path(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(times [T] s, points [T, 3] m)`` of a CSV ``t,x,y,z`` (s, mm), checked as
    :func:`read_csv` checks it."""
    reference = read_csv(path)
    return np.asarray(reference.times, np.float64), np.asarray(reference.points, np.float64)


def goal_table(goals_m: jax.Array, control_hz: float) -> Reference:
    """The reference whose goal of control period ``k`` is ``goals_m[k]`` (``[T, 3]`` m: at the
    period's end, ``(k + 1) / control_hz`` s), inside jit: a table, no checks."""
    count = goals_m.shape[0]
    zero = jnp.zeros(3, jnp.float32)
    return Reference(zero, zero, zero, jnp.float32(0.0), jnp.float32(0.0), jnp.float32(1.0),
                     jnp.arange(1, count + 1, dtype=jnp.float32) / control_hz,
                     jnp.asarray(goals_m, jnp.float32), jnp.asarray(True))


def stack(references: list[Reference]) -> Reference:
    """One :class:`Reference` with a leading ``[R]`` axis (vmap over it), the tables padded to
    the longest by holding their last point one second apart."""
    size = max(int(r.times.shape[0]) for r in references)

    def pad(reference: Reference) -> Reference:
        extra = size - int(reference.times.shape[0])
        if extra == 0:
            return reference
        times = jnp.concatenate([reference.times, reference.times[-1] + 1.0 + jnp.arange(extra)])
        points = jnp.concatenate([reference.points,
                                  jnp.repeat(reference.points[-1:], extra, axis=0)])
        return reference.replace(times=times, points=points)

    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *[pad(r) for r in references])


# ---------------------------------------------------------------------------------------------
# random draws (training)
# ---------------------------------------------------------------------------------------------
@struct.dataclass
class DrawRanges:
    """What :func:`draw` draws from (a pytree, in EnvParams).

    size_m: [2] m, the semi-axis range (uniform).
    period_s: [2] s, the period range (uniform in the rate: as many slow as fast laps).
    static_share: the probability of a static goal (a shape of zero size).
    """

    size_m: jax.Array
    period_s: jax.Array
    static_share: jax.Array


def draw(key: jax.Array, centre_m: jax.Array, ranges: DrawRanges) -> Reference:
    """A random shape around ``centre_m [3]`` m, inside jit: circle, ellipse (second semi-axis
    0.5 to 1 of the first) or figure-eight with equal odds, in the :data:`DRAW_PLANE`, in either
    direction, at a uniform phase; a static goal at ``centre_m`` with ``ranges.static_share``."""
    keys = jax.random.split(key, 7)
    kind = jax.random.randint(keys[0], (), 0, len(SHAPES))
    size = jax.random.uniform(keys[1], (), minval=ranges.size_m[0], maxval=ranges.size_m[1])
    ratio = jnp.where(kind == 1, jax.random.uniform(keys[2], (), minval=0.5, maxval=1.0), 1.0)
    rate = jax.random.uniform(keys[3], (), minval=1.0 / ranges.period_s[1],
                              maxval=1.0 / ranges.period_s[0])
    direction = jnp.where(jax.random.bernoulli(keys[4]), 1.0, -1.0)
    phase = jax.random.uniform(keys[5], (), minval=0.0, maxval=2.0 * jnp.pi)
    first, second = PLANES[DRAW_PLANE]
    moving = ~jax.random.bernoulli(keys[6], ranges.static_share)
    scale = jnp.where(moving, size, 0.0)
    axis_a = jnp.zeros(3).at[first].set(scale)
    axis_b = jnp.zeros(3).at[second].set(scale * ratio)
    harmonic = jnp.where(kind == 2, 2.0, 1.0)
    omega = jnp.where(moving, direction * 2.0 * jnp.pi * rate, 0.0)
    return _shape(centre_m, axis_a, axis_b, omega, phase, harmonic)


# ---------------------------------------------------------------------------------------------
# reachability
# ---------------------------------------------------------------------------------------------
def check_reachable(reference: Reference, duration_s: float, sample_hz: float,
                    reachable_m: np.ndarray, tolerance_mm: float, what: str = "reference"
                    ) -> None:
    """Refuse ``reference`` if, sampled at ``sample_hz`` over ``[0, duration_s]``, a point lies
    more than ``tolerance_mm`` from every position of ``reachable_m [N, 3]`` m (the goal set, the
    recorded positions): a :class:`InvalidReference` naming the first such point, its time, how far
    it is and the set's extent."""
    times = np.arange(math.floor(duration_s * sample_hz) + 1) / sample_hz
    path = np.asarray(positions(reference, jnp.asarray(times)), np.float64)
    check_points(times, path, reachable_m, tolerance_mm, what)


def check_points(times: np.ndarray, path_m: np.ndarray, reachable_m: np.ndarray,
                 tolerance_mm: float, what: str = "reference") -> None:
    """Refuse the points ``path_m [K, 3]`` m (at ``times [K]`` s) if one lies more than
    ``tolerance_mm`` from every position of ``reachable_m [N, 3]`` m, as
    :func:`check_reachable` does (its message)."""
    reachable = np.asarray(reachable_m, np.float64)
    if reachable.ndim != 2 or reachable.shape[1] != 3 or len(reachable) == 0:
        raise ValueError(f"reachable_m must be [N, 3] with N >= 1, got {reachable.shape}")
    path = np.asarray(path_m, np.float64).reshape(-1, 3)
    # [K] m, the distance of each point to its nearest reachable position: |p - r|^2 = |p|^2 +
    # |r|^2 - 2 p.r, a product for all pairs of _CHUNK points, about the set's mean (mm apart
    # within cm: float64 keeps far below a micrometre)
    mean = reachable.mean(axis=0)
    centred, points = reachable - mean, path - mean
    norms = (centred ** 2).sum(axis=1)
    squared = np.concatenate([np.empty(0)] + [
        ((chunk ** 2).sum(axis=1)[:, None] + norms[None] - 2.0 * chunk @ centred.T).min(axis=1)
        for chunk in np.split(points, range(_CHUNK, len(points), _CHUNK))])
    nearest = np.sqrt(np.maximum(squared, 0.0))
    outside = np.flatnonzero(~(nearest * MM_PER_M <= tolerance_mm))
    if len(outside) == 0:
        return
    first = outside[0]
    low, high = reachable.min(axis=0) * MM_PER_M, reachable.max(axis=0) * MM_PER_M
    extent = ", ".join(f"{axis} [{lo:.1f}, {hi:.1f}]" for axis, lo, hi in zip("xyz", low, high))
    raise InvalidReference(
        f"{what} refused: its point at t={times[first]:g} s, "
        f"{np.round(path[first] * MM_PER_M, 1).tolist()} mm, lies "
        f"{nearest[first] * MM_PER_M:.1f} mm from the nearest reachable position (tolerance "
        f"{tolerance_mm:g} mm); the reachable set ({len(reachable)} positions) spans {extent} mm")


# the settings of ReferenceConfig that only a replayed path reads, and only a shape
_REPLAY_FIELDS = tuple(field.name for field in dataclasses.fields(ReplaySettings))
_SHAPE_FIELDS = tuple(field.name for field in dataclasses.fields(ShapeSettings)
                      if field.name != "kind")


def reference_settings(entry: Any, what: str) -> ShapeSettings | ReplaySettings:
    """The :class:`ShapeSettings` (``centre_mm`` may stay None) or, for ``kind: replay``, the
    :class:`ReplaySettings` of a mapping of :class:`ReferenceConfig` fields (those it leaves out
    at their defaults); one :class:`InvalidReference` naming ``what`` for anything else: an
    unknown setting, or one that the kind does not read."""
    known = sorted(field.name for field in dataclasses.fields(ReferenceConfig))
    entry = {} if entry is None else entry  # every setting at its default
    if not isinstance(entry, Mapping):
        raise InvalidReference(f"{what}: expected a shape with some of {known}, got {entry!r}")
    unknown = sorted(set(map(str, entry)) - set(known))
    if unknown:
        raise InvalidReference(f"{what}: unknown setting(s) {unknown}; expected some of {known}")
    values = {**dataclasses.asdict(ReferenceConfig()), **entry}
    kind = str(values.pop("kind"))
    replayed = kind == REPLAY
    own, other = (_REPLAY_FIELDS, _SHAPE_FIELDS) if replayed else (_SHAPE_FIELDS, _REPLAY_FIELDS)
    stray = sorted(name for name in entry if name in other)
    if stray:
        raise InvalidReference(f"{what}: {stray} do not apply to kind {kind}; its settings are "
                               f"{['kind', *own]}")
    if replayed:
        return ReplaySettings(**{name: values[name] for name in _REPLAY_FIELDS})
    centre = values.pop("centre_mm")
    shape = {name: values[name] for name in _SHAPE_FIELDS if name != "centre_mm"}
    return ShapeSettings(kind=kind, **shape,
                         centre_mm=None if centre is None else tuple(float(v) for v in centre))
