"""The chain as data: the plan a run expands into, and the dry run that prints it."""

from __future__ import annotations

import subprocess
import sys

from pipeline import keys
from pipeline.__main__ import plan_table, run
from pipeline.chain import DRIVES_ARM, STAGES, Job, plan
from pipeline.config import PROJECT_ROOT
from pipeline.schemas import Stage


def train_key(cfg):
    return keys.key("train_ppo", cfg)


def summary(jobs: list[Job]) -> list[tuple[str, str, bool]]:
    return [(job.stage.value, job.label, job.result) for job in jobs]


def test_the_default_evaluate_plan_trains_each_policy_type_once(make_cfg):
    jobs = plan(make_cfg("stage=evaluate"), train_key)
    assert summary(jobs) == [
        ("collect", "", True), ("align", "", True), ("fit_model", "", True),
        ("train_ppo", "apg", True), ("train_ppo", "apg_rnn", False), ("evaluate", "", True)]
    # upstream of the requested stage nothing is forced
    forced = plan(make_cfg("stage=evaluate", "force=true"), train_key)
    assert [job.cfg.force for job in forced] == [False] * 5 + [True]
    assert all(job.cfg.force for job in plan(make_cfg("force=true"), train_key))
    # the two policy types may train side by side; the rest runs one after another
    assert [job.parallel for job in jobs] == ["", "", "", "train_ppo", "train_ppo", ""]


def test_a_policy_type_that_is_the_run_s_own_agent_trains_once(make_cfg):
    cfg = make_cfg("stage=evaluate", "agent=ppo_rnn", "evaluation.policies=[ppo_rnn]")
    assert summary(plan(cfg, train_key))[3:] == [("train_ppo", "ppo_rnn", True),
                                                ("evaluate", "", True)]


def test_evaluate_trains_only_the_policies_it_compares(make_cfg, sorolex_dir):
    # the baselines alone: nothing to train, in the run's own model or in the groups'
    cfg = make_cfg("stage=evaluate", "experiment=real_arm", f"robot.data_dir={sorolex_dir}",
                   "evaluation.policies=[]")
    assert not [job for job in plan(cfg, train_key) if job.stage is Stage.train_ppo]
    # a policy type other than the run's agent: that one, as the stage's result
    cfg = make_cfg("stage=evaluate", "agent=ppo_rnn", "evaluation.policies=[apg]")
    assert summary(plan(cfg, train_key))[3:] == [("train_ppo", "apg", True),
                                                ("evaluate", "", True)]
    # the whole chain trains its own agent besides
    cfg = make_cfg("stage=all", "agent=ppo_rnn", "evaluation.policies=[apg]")
    assert [job.label for job in plan(cfg, train_key)
            if job.stage is Stage.train_ppo] == ["ppo_rnn", "apg"]


def test_the_recorded_data_plan_fans_out_to_the_ensemble_and_both_groups(make_cfg, sorolex_dir):
    cfg = make_cfg("stage=evaluate", "experiment=real_arm", f"robot.data_dir={sorolex_dir}")
    jobs = plan(cfg, train_key)
    labels = [(job.stage.value, job.label) for job in jobs]
    own = [("collect", ""), ("align", ""), ("fit_model", ""), ("fit_model", "model.seed=1"),
           ("fit_model", "model.seed=2"), ("train_ppo", "ppo_ff"), ("train_ppo", "ppo_rnn")]
    group = [("collect", ""), ("align", ""), ("fit_model", ""), ("fit_model", "model.seed=1"),
             ("fit_model", "model.seed=2"), ("train_ppo", "ppo_ff"), ("train_ppo", "ppo_rnn")]
    expected = own + [
        (stage, f"cross-model {direction}" + (f", {label}" if label else ""))
        for direction in ("A->B", "B->A") for stage, label in group] + [("evaluate", "")]
    assert labels == expected
    # only the requested config's own jobs are the stages' results
    assert [job.label for job in jobs if job.result] == ["", "", "", "ppo_ff", ""]
    # what evaluate looks up is exactly what the plan trains
    _, inputs = keys.evaluate_spec(cfg)
    trained = {keys.key("train_ppo", job.cfg) for job in jobs if job.stage is Stage.train_ppo}
    looked_up = {key for name, key in inputs.items() if "train_ppo" in name}
    assert looked_up <= trained
    fitted = {keys.key("fit_model", job.cfg) for job in jobs if job.stage is Stage.fit_model}
    assert {inputs["cross_model/A->B/fit_model"], inputs["cross_model/B->A/fit_model"]} <= fitted


def test_a_real_arm_is_driven_only_by_the_stage_named(make_cfg):
    assert DRIVES_ARM == {Stage.collect, Stage.guard, Stage.control, Stage.adapt,
                          Stage.improve}
    assert all(STAGES[stage].drives_arm for stage in DRIVES_ARM)
    jobs = plan(make_cfg("stage=evaluate", "robot=ros2"), train_key)
    assert not [job for job in jobs if job.stage in DRIVES_ARM]


def test_the_plan_table_says_what_is_reused(make_cfg):
    cfg = make_cfg("stage=align", "experiment=quick")
    jobs = plan(cfg, train_key)
    assert plan_table(jobs).splitlines()[1:] == [
        f"collect  -    {keys.key('collect', cfg)}  runs",
        f"align    -    {keys.key('align', cfg)}  runs"]
    run(cfg)
    assert [line.split()[-1] for line in plan_table(jobs).splitlines()[1:]] == ["reused"] * 2
    forced = make_cfg("stage=align", "experiment=quick", "force=true")
    assert plan_table(plan(forced, train_key)).splitlines()[-1].endswith("recomputed (force)")


def test_dry_run_prints_the_plan_and_writes_nothing(tmp_path):
    out = tmp_path / "outputs"
    done = subprocess.run(
        [sys.executable, "-m", "pipeline", "--dry-run", "stage=evaluate",
         f"paths.output_dir={out}"], cwd=PROJECT_ROOT, capture_output=True, text=True,
        timeout=300)
    assert done.returncode == 0, done.stderr
    text = done.stdout + done.stderr
    assert "dry run: 6 jobs, nothing runs" in text
    assert "train_ppo  apg_rnn" in text
    assert not (out / "artifacts").exists()
