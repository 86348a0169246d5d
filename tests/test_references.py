"""References to follow: shapes, tables, CSV and replayed paths, random draws, reachability."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline.arm import references as R
from pipeline.schemas import ConfigError


def mm(reference, *times):
    return np.asarray(R.positions(reference, jnp.asarray(times, jnp.float32))) * 1000.0


def test_circle_and_figure_eight_by_hand():
    circle = R.shape(R.ShapeSettings("circle", (10.0, 0.0, -100.0), 5.0, period_s=20.0))
    # a quarter lap every 5 s, counter-clockwise from +x toward +z
    np.testing.assert_allclose(mm(circle, 0.0, 5.0, 10.0, 20.0),
                               [[15, 0, -100], [10, 0, -95], [5, 0, -100], [15, 0, -100]],
                               atol=1e-3)
    clockwise = R.shape(R.ShapeSettings("circle", (10.0, 0.0, -100.0), 5.0, period_s=20.0,
                                        direction=-1))
    np.testing.assert_allclose(mm(clockwise, 5.0), [[10, 0, -105]], atol=1e-3)
    ellipse = R.shape(R.ShapeSettings("ellipse", (0.0, 0.0, 0.0), 4.0, 2.0, 8.0, phase_deg=90.0,
                                      plane="xy"))
    np.testing.assert_allclose(mm(ellipse, 0.0, 2.0), [[0, 2, 0], [-4, 0, 0]], atol=1e-3)
    # figure-eight: x = 5 cos(theta), z = 5 sin(2 theta); it crosses itself at the centre
    eight = R.shape(R.ShapeSettings("figure_eight", (0.0, 0.0, 0.0), 5.0, period_s=20.0))
    np.testing.assert_allclose(mm(eight, 2.5, 5.0, 15.0),
                               [[5 / math.sqrt(2), 0, 5], [0, 0, 0], [0, 0, 0]], atol=1e-3)


@pytest.mark.parametrize("change, words", [
    ({"kind": "square"}, "kind 'square'"), ({"plane": "xx"}, "plane 'xx'"),
    ({"size_mm": -1.0}, "size_mm=-1.0"), ({"period_s": float("nan")}, "period_s=nan"),
    ({"direction": 2}, "direction 2")])
def test_bad_shape_settings_name_the_setting(change, words):
    settings = {"kind": "circle", "centre_mm": (0.0, 0.0, 0.0), **change}
    with pytest.raises(R.InvalidReference, match=words):
        R.shape(R.ShapeSettings(**settings))


def test_waypoints_at_a_constant_speed_then_held():
    path = R.waypoints(np.array([[0, 0, 0], [10, 0, 0], [10, 0, 0], [10, 10, 0]]), 2.0, 1.0)
    np.testing.assert_allclose(path.times, [1.0, 6.0, 11.0])  # the repeated point skipped
    np.testing.assert_allclose(mm(path, 0.0, 3.5, 8.5, 100.0),
                               [[0, 0, 0], [5, 0, 0], [10, 5, 0], [10, 10, 0]], atol=1e-3)


def test_a_timed_csv_in_mm(tmp_path):
    path = tmp_path / "path.csv"
    path.write_text("t,x,y,z,note\n0,30,352,200,a\n2,34,352,200,b\n4,34,352,196,c\n")
    reference = R.read_csv(path)
    np.testing.assert_allclose(mm(reference, 1.0, 3.0, 9.0),
                               [[32, 352, 200], [34, 352, 198], [34, 352, 196]], atol=1e-3)


@pytest.mark.parametrize("rows, words", [
    ("0,30,352,200\n2,31,352,200\n2,32,352,200\n", "times must increase; row 2 has t=2 s"),
    ("0,30,352,200\n1,nan,352,200\n", "row 1 is not finite"),
    ("0,0.030,0.352,0.200\n1,0.031,0.352,0.200\n", "look like metres"),
])
def test_a_bad_csv_is_one_line_naming_the_file(tmp_path, rows, words):
    path = tmp_path / "bad.csv"
    path.write_text("t,x,y,z\n" + rows)
    with pytest.raises(ConfigError, match=words) as err:  # the known-error path
        R.read_csv(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_a_csv_without_its_columns(tmp_path):
    path = tmp_path / "cols.csv"
    path.write_text("time,x,y\n0,1,2\n")
    with pytest.raises(R.InvalidReference, match=r"missing column\(s\) \['t', 'z'\]"):
        R.read_csv(path)


def test_replayed_path_slowed():
    times = np.array([10.0, 10.1, 10.2, 10.3, 10.4])  # a recording's clock
    recorded = np.array([[0.0, 0, 0], [0.001, 0, 0], [0.002, 0, 0], [0.003, 0, 0],
                         [0.004, 0, 0]])
    replayed = R.replay(times, recorded, slow_down=4.0)
    np.testing.assert_allclose(replayed.times, [0.0, 0.4, 0.8, 1.2, 1.6], atol=1e-6)
    np.testing.assert_allclose(mm(replayed, 0.2, 1.2, 5.0)[:, 0], [0.5, 3.0, 4.0], atol=1e-4)
    with pytest.raises(R.InvalidReference, match=r"slow_down=0.0: expected a finite number > 0"):
        R.replay(times, recorded, slow_down=0.0)


def walk_m(seconds: float, rate_hz: float = 10.0, offset_mm: float = 0.0):
    """A measured path for the replays: x = offset + t mm (1 mm/s), at ``rate_hz``."""
    times = np.arange(round(seconds * rate_hz) + 1) / rate_hz
    points = np.zeros((len(times), 3))
    points[:, 0] = (offset_mm + times) / 1000.0
    return times, points


def test_replayed_stretches_spread_over_every_recording():
    paths = {"a": walk_m(10.0), "b": walk_m(5.0, offset_mm=100.0)}
    settings = R.ReplaySettings(slow_down=2.0, start_s=1.0)
    # 8 s followed at half speed: 4 s of path; stretches may begin at 1 .. 6 s of a (51 samples)
    # and 1 .. 1 s of b (1 sample): 52 starts, 4 stretches spread over them: samples 0, 13, 26, 39
    stretches = R.replay_stretches(paths, settings, seconds=8.0, count=4)
    begins = [mm(stretch, 0.0)[0, 0] for stretch in stretches]
    np.testing.assert_allclose(begins, [1.0, 2.3, 3.6, 4.9], atol=1e-4)
    for stretch, begin in zip(stretches, begins, strict=True):
        # half the path's speed, over 8 s: 4 mm, then held at its last point
        np.testing.assert_allclose(mm(stretch, 2.0, 8.0, 9.0)[:, 0] - begin, [1.0, 4.0, 4.0],
                                   atol=1e-4)
    # 52 stretches: the last begins in b, at 1 s
    last = R.replay_stretches(paths, settings, seconds=8.0, count=52)[-1]
    np.testing.assert_allclose(mm(last, 0.0, 8.0)[:, 0], [101.0, 105.0], atol=1e-4)
    only_b = R.replay_stretches(paths, R.ReplaySettings(run="b", slow_down=2.0), 8.0, 1)[0]
    np.testing.assert_allclose(mm(only_b, 0.0)[0, 0], 100.0, atol=1e-4)


@pytest.mark.parametrize("settings, seconds, words", [
    (R.ReplaySettings(run="c"), 8.0, r"run 'c' is not among the recordings \['a', 'b'\]"),
    (R.ReplaySettings(slow_down=1.0, start_s=4.0), 8.0,
     r"no recording holds 8 s of path after start_s=4 s \(8 s followed at slow_down=1\); the "
     r"longest lasts 10.0 s"),
    (R.ReplaySettings(start_s=-1.0), 8.0, r"start_s=-1.0: expected a finite number >= 0 s"),
    (R.ReplaySettings(slow_down=float("nan")), 8.0, r"slow_down=nan: expected a finite number"),
])
def test_bad_replays_are_refused_by_name(settings, seconds, words):
    paths = {"a": walk_m(10.0), "b": walk_m(5.0)}
    with pytest.raises(R.InvalidReference, match=r"^evaluation.references walk: " + words):
        R.replay_stretches(paths, settings, seconds, 4, "evaluation.references walk")


def test_the_rest_of_a_recording_replayed_from_its_start():
    paths = {"a": walk_m(10.0), "b": walk_m(5.0, offset_mm=100.0)}
    name, rest = R.replay_rest(paths, R.ReplaySettings(run="b", slow_down=3.0, start_s=2.0))
    assert name == "b"
    assert float(rest.times[-1]) == pytest.approx(9.0)  # 3 s of path, 3 times slower
    np.testing.assert_allclose(mm(rest, 0.0, 4.5, 9.0)[:, 0], [102.0, 103.5, 105.0], atol=1e-4)
    assert R.replay_rest(paths, R.ReplaySettings())[0] == "a"  # no run: the first
    with pytest.raises(R.InvalidReference, match=r"b lasts 5.0 s, nothing to replay after "
                                                 r"start_s=6 s"):
        R.replay_rest(paths, R.ReplaySettings(run="b", start_s=6.0))


def test_a_replayed_csv_and_the_recordings_a_replay_needs(tmp_path):
    path = tmp_path / "walk.csv"
    path.write_text("t,x,y,z\n0,30,353,200\n0.5,31,353,200\n1,33,353,200\n")
    csv = R.ReplaySettings(file=str(path))
    paths = R.measured_paths(csv, {}, "walk")
    times, points = paths[str(path)]
    np.testing.assert_allclose(times, [0, 0.5, 1.0])
    np.testing.assert_allclose(points[:, 0], [0.030, 0.031, 0.033])
    recorded = {"a": walk_m(10.0)}
    assert R.measured_paths(R.ReplaySettings(), recorded, "walk") is recorded
    with pytest.raises(R.InvalidReference, match=r"walk: a replayed path needs the recordings"):
        R.measured_paths(R.ReplaySettings(), {}, "walk")
    path.write_text("t,x,y,z\n0,0.030,0.353,0.200\n1,0.031,0.353,0.200\n")
    with pytest.raises(R.InvalidReference, match=r"look like metres"):
        R.measured_paths(csv, {}, "walk")


def test_reference_settings_read_shapes_and_replays_and_refuse_what_the_kind_ignores():
    assert R.reference_settings({"kind": "replay", "run": "a", "slow_down": 2},
                                "walk") == R.ReplaySettings(run="a", slow_down=2.0)
    assert R.reference_settings({"period_s": 10}, "fast") == R.ShapeSettings(
        "circle", None, 5.0, period_s=10.0)
    with pytest.raises(R.InvalidReference, match=r"^walk: \['size_mm'\] do not apply to kind "
                                                 r"replay; its settings are \['kind', 'run', "
                                                 r"'file', 'slow_down', 'start_s'\]$"):
        R.reference_settings({"kind": "replay", "size_mm": 3}, "walk")
    with pytest.raises(R.InvalidReference, match=r"^fast: \['slow_down'\] do not apply to kind "
                                                 r"circle"):
        R.reference_settings({"slow_down": 3}, "fast")
    with pytest.raises(R.InvalidReference, match=r"expected one of \('circle', 'ellipse', "
                                                 r"'figure_eight', 'replay'\)"):
        R.shape(R.reference_settings({"kind": "spiral"}, "odd"))


def test_shapes_and_tables_stack_and_run_under_jit_and_vmap():
    circle = R.shape(R.ShapeSettings("circle", (0.0, 0.0, 0.0), 5.0, period_s=20.0))
    table = R.waypoints(np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0]]), 2.0)
    both = R.stack([circle, table, R.static(jnp.array([0.001, 0.002, 0.003]))])
    assert both.times.shape == (3, 3) and both.points.shape == (3, 3, 3)
    at = jax.jit(jax.vmap(R.position, in_axes=(0, None)))(both, 5.0) * 1000.0
    np.testing.assert_allclose(at, [[0, 0, 5], [10, 0, 0], [1, 2, 3]], atol=1e-3)
    goals = jnp.array([[0.0, 0, 0], [0.001, 0, 0], [0.002, 0, 0]])
    by_period = R.goal_table(goals, 2.0)  # goal k at the end of period k: (k + 1) / 2 s
    np.testing.assert_allclose(mm(by_period, 0.5, 1.0, 1.5)[:, 0], [0, 1, 2], atol=1e-4)


def test_draws_within_their_ranges_in_the_xz_plane():
    ranges = R.DrawRanges(jnp.array([0.002, 0.004]), jnp.array([10.0, 30.0]), jnp.float32(0.0))
    keys = jax.random.split(jax.random.PRNGKey(0), 256)
    centre = jnp.array([0.03, 0.35, 0.2])
    drawn = jax.jit(jax.vmap(R.draw, in_axes=(0, None, None)))(keys, centre, ranges)
    size = np.asarray(drawn.axis_a[:, 0])
    assert (size >= 0.002 - 1e-7).all() and (size <= 0.004 + 1e-7).all()
    assert (np.asarray(drawn.axis_a[:, 1:]) == 0).all() and (np.asarray(drawn.axis_b[:, :2]) == 0).all()
    ratio = np.asarray(drawn.axis_b[:, 2]) / size
    assert (ratio >= 0.5 - 1e-6).all() and (ratio <= 1 + 1e-6).all()
    period = 2 * np.pi / np.abs(np.asarray(drawn.omega))
    assert (period >= 10.0 - 1e-3).all() and (period <= 30.0 + 1e-3).all()
    assert 0.3 < (np.asarray(drawn.omega) > 0).mean() < 0.7  # both directions
    assert set(np.asarray(drawn.harmonic).tolist()) == {1.0, 2.0}
    np.testing.assert_allclose(drawn.centre, np.broadcast_to(centre, (256, 3)))
    still = jax.vmap(R.draw, in_axes=(0, None, None))(keys, centre, ranges.replace(
        static_share=jnp.float32(1.0)))
    at = jax.vmap(R.position, in_axes=(0, None))(still, 7.3)
    np.testing.assert_array_equal(at, np.broadcast_to(centre, (256, 3)))


def test_a_reference_leaving_the_reachable_set_is_refused_naming_where():
    reachable = np.stack([np.linspace(0.0, 0.01, 101), np.zeros(101), np.zeros(101)], axis=1)
    inside = R.waypoints(np.array([[1, 0, 0], [9, 0, 0]]), 1.0)
    R.check_reachable(inside, 10.0, 2.0, reachable, 0.5)  # no error
    leaving = R.waypoints(np.array([[5, 0, 0], [5, 0, 4]]), 1.0)  # 1 mm up per second
    with pytest.raises(ConfigError) as err:
        R.check_reachable(leaving, 4.0, 2.0, reachable, 1.2, "test path")
    message = str(err.value)
    assert "test path refused: its point at t=1.5 s, [5.0, 0.0, 1.5] mm, lies 1.5 mm" in message
    assert "x [0.0, 10.0], y [0.0, 0.0], z [0.0, 0.0] mm" in message
