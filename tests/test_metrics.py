"""Episode metrics on hand-made trajectories with known answers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from pipeline.evaluation.metrics import episode_metrics, hold_metrics, plant_gap, summarize

LIMITS = SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0)


def straight_line_episode():
    """Two episodes, 4 steps: one closes 8 mm to 0.5 mm, one stalls 4 mm away."""
    goal = np.array([0.0, 0.0, 0.0])
    approach = np.array([8.0, 4.0, 2.0, 0.9, 0.5]) / 1000  # mm -> m, along x
    stall = np.array([6.0, 5.0, 4.0, 4.0, 4.0]) / 1000
    positions = np.zeros((2, 5, 3))
    positions[0, :, 0] = approach
    positions[1, :, 2] = stall
    commands = np.array([
        [[2, 2, 2], [3, 2, 2], [3, 2, 2], [4, 2, 2]],  # changes: 1, 0, 1 kPa on one valve
        [[2, 2, 2], [2, 2, 2], [7.5, 2, 2], [2, 2, 2]],  # one step above p_max
    ], float)
    return positions, np.stack([goal, goal]), commands


def test_metrics_of_hand_made_episodes():
    m = episode_metrics(*straight_line_episode(), LIMITS)
    np.testing.assert_allclose(m["final_distance_mm"], [0.5, 4.0])
    np.testing.assert_allclose(m["min_distance_mm"], [0.5, 4.0])
    assert m["success_1mm"].tolist() == [True, False]
    assert m["success_3mm"].tolist() == [True, False]
    assert m["steps_to_1mm"].iloc[0] == 3 and np.isnan(m["steps_to_1mm"].iloc[1])
    assert m["steps_to_3mm"].iloc[0] == 2
    # mean |change| over 3 transitions x 3 valves: (1 + 0 + 1) / 9 and (5.5 + 5.5) / 9
    np.testing.assert_allclose(m["smoothness_kpa"], [2 / 9, 11 / 9])
    assert m["steps_above_limits"].tolist() == [0, 1]
    np.testing.assert_allclose(m["time_above_limits"], [0.0, 0.25])


def test_moving_goals_are_followed_per_row():
    positions = np.zeros((1, 3, 3))
    goals = np.array([[[0.001, 0, 0], [0.002, 0, 0], [0, 0, 0]]])
    m = episode_metrics(positions, goals, np.full((1, 2, 3), 2.0), LIMITS)
    assert m["final_distance_mm"].item() == pytest.approx(0.0)
    assert m["steps_to_1mm"].item() == 0


def test_shape_errors_are_clear():
    positions, goals, commands = straight_line_episode()
    with pytest.raises(ValueError, match="commands must be"):
        episode_metrics(positions, goals, commands[:, :2], LIMITS)
    with pytest.raises(ValueError, match="positions must be"):
        episode_metrics(positions[0], goals, commands, LIMITS)


def test_plant_gap_and_summary():
    learned = pd.DataFrame({"final_distance_mm": [0.5, 1.0]})
    plant = pd.DataFrame({"final_distance_mm": [1.5, 0.5]})
    gap = plant_gap(learned, plant, np.zeros((2, 3)), np.array([[0.003, 0.004, 0], [0, 0, 0]]))
    np.testing.assert_allclose(gap["final_gap_mm"], [1.0, -0.5])
    np.testing.assert_allclose(gap["final_position_gap_mm"], [5.0, 0.0])
    m = episode_metrics(*straight_line_episode(), LIMITS).assign(policy=["a", "b"])
    s = summarize(m, ["policy"])
    assert s["median_final_mm"].tolist() == [0.5, 4.0]
    assert s["time_above_limits"].tolist() == [0.0, 0.25]


def test_hold_after_the_first_arrival_by_hand():
    distance = np.array([
        [5.0, 2.0, 0.8, 1.2, 0.9, 1.4],  # arrives at t=2, leaves, ends at 1.4 mm: held
        [5.0, 4.0, 3.0, 2.0, 2.0, 2.0],  # never within 1 mm
        [0.5, 0.5, 0.5, 0.5, 0.5, 2.0],  # within from the start, lost at the end: not held
        [9.0, 8.0, 7.0, 6.0, 5.0, 1.0],  # arrives at the last time
    ])
    hold = hold_metrics(distance)
    # times 2..5: 0.8, 1.2, 0.9, 1.4 -> 2 of 4 within 1 mm; all 6 times, 5 within; 1 of 1
    np.testing.assert_allclose(hold["within_1mm_after_arrival"], [0.5, np.nan, 5 / 6, 1.0])
    np.testing.assert_allclose(hold["max_after_arrival_mm"], [1.4, np.nan, 2.0, 1.0])
    np.testing.assert_allclose(hold["held_1.5mm"], [1.0, np.nan, 0.0, 1.0])


def test_summary_counts_the_hold_over_the_arrivals_only():
    goal = np.zeros(3)
    distance = np.array([[5.0, 0.8, 1.2, 1.4], [5.0, 0.5, 3.0, 2.5], [6.0, 5.0, 4.0, 4.0]])
    positions = np.zeros((3, 4, 3))
    positions[..., 0] = distance / 1000
    m = episode_metrics(positions, np.stack([goal] * 3), np.full((3, 3, 3), 2.0), LIMITS)
    np.testing.assert_allclose(m["held_1.5mm"], [1.0, 0.0, np.nan])
    s = summarize(m.assign(policy="a"), ["policy"]).iloc[0]
    assert s["arrived_1mm"] == pytest.approx(2 / 3)
    assert s["held_arrivals"] == pytest.approx(0.5)  # 1 of the 2 that arrived, not 1 of 3
    # shares after arrival: 1 of 3 (0.8; 1.2, 1.4 out) and 1 of 3 (0.5; 3.0, 2.5 out)
    assert s["within_1mm_after_arrival"] == pytest.approx(1 / 3)
    assert s["median_max_after_arrival_mm"] == pytest.approx((1.4 + 3.0) / 2)
