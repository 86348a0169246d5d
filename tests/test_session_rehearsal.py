"""The session-rehearsal study's plan: which runs each model trains on, counted by hand."""

import numpy as np

from experiments.session_rehearsal import plan
from pipeline.data.runs import Run
from pipeline.dynamics import cv


def _run(run_id: str, steps: int) -> Run:
    return Run(run_id, np.arange(steps) / 10.0, np.zeros((steps, 3), np.float32),
               np.zeros((steps, 3), np.float32))


def test_plan_trains_each_model_on_what_it_names():
    runs = [_run("a", 100), _run("b", 200), _run("c", 300)]
    extra, models = plan(runs, [5.0], hz=10.0, seed=3)
    # per run: a fold, a rehearsal on 5 s and a half; then the pooled halves and all runs
    assert list(models) == ["fold/a", "rehearsal_5s/a", "half/a", "fold/b", "rehearsal_5s/b",
                            "half/b", "fold/c", "rehearsal_5s/c", "half/c", "pooled_halves",
                            "all_runs"]
    fold, held_out = models["fold/a"]
    assert fold.train_ids == ("b", "c") and held_out == "a" and fold.seed == 3
    # 5 s at 10 Hz is 50 steps; the mean run has 200, so the context is repeated 4 times
    rehearsal, _ = models["rehearsal_5s/a"]
    copies = [run for run in extra if run.run_id.startswith("a~5s~")]
    assert rehearsal.train_ids == ("b", "c", "a~5s~0", "a~5s~1", "a~5s~2", "a~5s~3")
    assert [len(run) for run in copies] == [50] * 4
    np.testing.assert_array_equal(copies[0].times_s, runs[0].times_s[:50])
    half, _ = models["half/c"]
    assert half.train_ids == ("a", "b", "c~half")
    assert len(next(run for run in extra if run.run_id == "c~half")) == 150
    assert models["pooled_halves"] == (cv.Member(("a~half", "b~half", "c~half"), None, 3), None)
    assert models["all_runs"][0].train_ids == ("a", "b", "c")
    # windows of 20 steps: 81 + 181 + 281 in the whole runs, 31 in each context copy
    starts = cv._member_windows([*runs, *extra], [m for m, _ in models.values()], 20, 1)
    counts = dict(zip(models, map(len, starts)))
    assert counts["fold/a"] == 181 + 281
    assert counts["rehearsal_5s/a"] == 181 + 281 + 4 * 31
    assert counts["half/c"] == 81 + 181 + 131
    assert counts["pooled_halves"] == 31 + 81 + 131


def test_the_head_of_a_run_is_its_first_steps_under_another_name():
    run = Run("r", np.arange(5) / 10.0, np.arange(15, dtype=np.float32).reshape(5, 3),
              np.arange(15, dtype=np.float32).reshape(5, 3) / 100)
    head = run.head(2, "r~2")
    assert head.run_id == "r~2" and len(head) == 2
    np.testing.assert_array_equal(head.times_s, [0.0, 0.1])
    np.testing.assert_array_equal(head.pressures_kpa, [[0, 1, 2], [3, 4, 5]])
    np.testing.assert_allclose(head.positions_m, [[0, 0.01, 0.02], [0.03, 0.04, 0.05]])
