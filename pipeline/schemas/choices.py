"""The closed sets of options the config schemas use (enums that compare equal to their
values, so YAML and the command line give plain strings).
"""

from __future__ import annotations

from enum import Enum


class Choice(str, Enum):
    """A closed set of options: compares equal to, prints and formats as its value."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


class Stage(Choice):
    collect = "collect"
    align = "align"
    fit_model = "fit_model"
    train_ppo = "train_ppo"
    evaluate = "evaluate"
    twin = "twin"  # the simulated arm as a ROS 2 node (not part of `all`)
    guard = "guard"  # the arm-side deadman and rating filter as a ROS 2 node (not part of `all`)
    control = "control"  # a trained policy drives the arm (not part of `all`)
    calibrate = "calibrate"  # fit the simulated arm to recorded runs (not part of `all`)
    adapt = "adapt"  # calibrate model and policy to the session of the day (not part of `all`)
    improve = "improve"  # rounds of drive, record, refit, retrain on the arm (not part of `all`)
    all = "all"


class RobotKind(Choice):
    sim = "sim"
    ros2 = "ros2"
    sorolex_csv = "sorolex_csv"
    plotjuggler_csv = "plotjuggler_csv"
    rosbag = "rosbag"


class ModelProtocol(Choice):
    """How fit_model selects and scores the model (``dataset.protocol``)."""

    auto = "auto"  # cv for recorded data (every robot but sim), split for the simulated arm
    cv = "cv"  # leave-one-run-out cross-validation, then the model is trained on all runs
    split = "split"  # one seeded split of the runs (train_fraction, split_seed)


class GapPolicy(Choice):
    error = "error"  # a mocap gap longer than max_gap_s aborts align, naming the run and time
    split = "split"  # the run is split at the gap into runs '<id>#0', '<id>#1', ... (counted)


class EnvName(Choice):
    learned = "learned"  # the fitted model of the fit_model artifact
    sim = "sim"  # the simulated arm itself
    gymnax = "gymnax"  # a standard gymnax environment (env.gymnax_name), to check the PPO


class GoalSource(Choice):
    predicted = "predicted"  # the model's open-loop predictions along the runs: reachable in it
    measured = "measured"  # the runs' recorded positions


class ActionMode(Choice):
    absolute = "absolute"  # the action sets each valve's pressure on its range
    incremental = "incremental"  # the action changes each valve's last command


class Task(Choice):
    reach = "reach"  # one goal per episode, reached and held
    track = "track"  # a moving reference: each control period's goal is where it is then


class GoalMode(Choice):
    data = "data"  # uniform over the positions seen in the data
    perturb = "perturb"  # the paper's: the initial pose plus N(0, 1) * goal_perturbation_m


class ModelGrid(Choice):
    clock = "clock"  # a regular grid at model_hz
    commands = "commands"  # locked to the command times


class WindowOrder(Choice):
    permuted = "permuted"  # windows drawn at random (a fresh permutation per epoch)
    sequential = "sequential"  # windows in time order


class LrSchedule(Choice):
    constant = "constant"
    cosine = "cosine"  # linear warmup, cosine decay to the end


class ReferencePose(Choice):
    run_start = "run_start"  # the pose the window's run started from (as an env sees at reset)
    window_start = "window_start"  # the window's own first pose


class Cell(Choice):
    lstm = "lstm"
    gru = "gru"


class ModelLoss(Choice):
    """What the dynamics model's training minimizes over its open-loop windows."""

    mse = "mse"  # mean squared error of the standardized position, per axis
    distance = "distance"  # mean Euclidean distance to the measured position (the score)


class Activation(Choice):
    tanh = "tanh"
    relu = "relu"
