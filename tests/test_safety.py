"""The safe-set projection: hand-computed cases and properties over arbitrary inputs."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.arm.limits import assert_safe, validate_limits
from pipeline.arm.safety import SafeSet, on_boundary, project

LIMITS = SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0, preload=2.0)
SAFE = SafeSet.from_limits(LIMITS)
project_jit = jax.jit(project)


@pytest.mark.parametrize(
    ("command", "expected"),
    [
        ([2.0, 2.0, 2.0], [2.0, 2.0, 2.0]),  # inside: unchanged
        ([-1.0, 9.0, 3.0], [0.0, 7.0, 3.0]),  # box only
        ([10.0, 10.0, 10.0], [13 / 3, 13 / 3, 13 / 3]),  # 3 (10 - lam) = 13
        ([7.0, 7.0, 0.0], [6.5, 6.5, 0.0]),  # (7 - lam) * 2 + clip(0 - lam) = 13 -> lam = 0.5
        ([9.0, 6.0, 1.0], [7.0, 5.5, 0.5]),  # box first binds valve 0: 7 + (6-l) + (1-l) = 13
    ],
)
def test_projection_hand_computed(command, expected):
    np.testing.assert_allclose(project_jit(jnp.array(command), SAFE), expected, atol=2e-4)


finite = st.floats(-1e4, 1e4, allow_nan=False, width=32)


@settings(max_examples=300, deadline=None)
@given(st.lists(finite, min_size=3, max_size=3))
def test_projection_lands_in_the_safe_set_and_is_idempotent(command):
    p = np.asarray(project_jit(jnp.array(command, jnp.float32), SAFE), np.float64)
    assert np.all(p >= LIMITS.p_min) and np.all(p <= LIMITS.p_max)
    assert p.sum() <= LIMITS.sum_max
    assert_safe(p, LIMITS)  # the hardware gate agrees
    again = np.asarray(project_jit(jnp.asarray(p, jnp.float32), SAFE))
    np.testing.assert_allclose(again, p, atol=1e-4)


@settings(max_examples=100, deadline=None)
@given(st.lists(finite, min_size=3, max_size=3), st.lists(st.floats(0, 7, width=32),
                                                          min_size=3, max_size=3))
def test_projection_is_the_nearest_safe_point(command, other):
    """No safe point is closer to the command than its projection (up to float32 slack)."""
    x = np.asarray(command, np.float64)
    p = np.asarray(project_jit(jnp.asarray(x, jnp.float32), SAFE), np.float64)
    q = np.asarray(other, np.float64)
    if q.sum() > LIMITS.sum_max:
        q *= LIMITS.sum_max / q.sum()
    assert np.linalg.norm(x - p) <= np.linalg.norm(x - q) + 1e-3 * (1 + np.abs(x).max())


def test_on_boundary_by_hand():
    commands = np.array([
        [2.0, 2.0, 2.0],  # inside
        [0.0, 3.0, 3.0],  # a valve at p_min
        [7.0, 1.0, 1.0],  # a valve at p_max
        [13 / 3, 13 / 3, 13 / 3],  # the sum at sum_max, no valve at a bound
        [4.0, 4.0, 4.98],  # the sum 0.02 kPa inside: not on it
        [4.0, 4.0, 4.995],  # the sum within the 0.01 kPa tolerance
        [np.nan, 2.0, 2.0],  # no command
    ])
    np.testing.assert_array_equal(on_boundary(commands, SAFE),
                                  [False, True, True, True, False, True, False])
    # what the projection returns for a command asking for more lies on the boundary
    assert on_boundary(np.asarray(project_jit(jnp.array([10.0, 10.0, 10.0]), SAFE)), SAFE)
    assert on_boundary(commands.reshape(7, 1, 3), SAFE).shape == (7, 1)


def test_projection_maps_nan_and_infinity_into_the_set():
    p = np.asarray(project_jit(jnp.array([jnp.nan, jnp.inf, -jnp.inf]), SAFE))
    assert np.all(np.isfinite(p)) and p.sum() <= 13.0 and np.all((p >= 0) & (p <= 7))


def test_projection_batches():
    batch = jax.random.normal(jax.random.key(0), (64, 3)) * 10
    out = project_jit(batch, SAFE)
    assert out.shape == (64, 3)
    assert float(out.sum(-1).max()) <= 13.0


def test_hardware_gate_refuses_unsafe_commands():
    for bad in ([7.5, 0, 0], [-0.1, 1, 1], [6, 6, 2], [np.nan, 1, 1]):
        with pytest.raises(ValueError, match="refusing"):
            assert_safe(np.array(bad), LIMITS)


@pytest.mark.parametrize("limits", [
    dict(p_min=5.0, p_max=4.0, sum_max=13.0, preload=2.0),
    dict(p_min=5.0, p_max=7.0, sum_max=13.0, preload=5.0),
    dict(p_min=0.0, p_max=7.0, sum_max=5.0, preload=2.0),
])
def test_inconsistent_limits_are_rejected(limits):
    with pytest.raises(ValueError, match=r"robot\.limits"):
        validate_limits(SimpleNamespace(**limits))


@settings(max_examples=100, deadline=None)
@given(st.floats(-5, 0, width=64), st.floats(0.1, 9, width=64), st.floats(1, 20, width=64),
       st.lists(finite, min_size=3, max_size=3))
def test_float32_projection_respects_float64_limits(p_min, width, sum_room, command):
    """Bounds such as 6.9 kPa have no exact float32; the projection still never exceeds them."""
    limits = SimpleNamespace(p_min=p_min, p_max=p_min + width, sum_max=3 * p_min + sum_room)
    safe = SafeSet.from_limits(limits)
    p = np.asarray(project_jit(jnp.array(command, jnp.float32), safe), np.float64)
    assert_safe(p, limits)
