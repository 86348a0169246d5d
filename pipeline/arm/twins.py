"""The calibrated twin: the simulated arm with physics fitted to an arm, as a plant.

Where its physics come from (:func:`twin_physics`): a ``calibrate`` artifact (its key in the
artifact store or its folder, holding ``physics.json``; what ``robot.physics_from`` reads), or a
simulated robot config of the ``robot`` group by name (``conf/robot/<name>.yaml``, e.g.
``sim_sorolex``: the physics calibrated to the paper's runs, kept in the config so that nothing
needs the calibrate artifact at run time). :func:`twin_sim_params` makes the simulator's
parameters of them: nominal physics (no per-session draw; a plant is one arm) integrated at the
default motion-capture rate.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import yaml

from pipeline import PROJECT_ROOT
from pipeline.infra.artifacts import ArtifactStore, MissingArtifactError
from pipeline.schemas import ConfigError, MocapConfig, SimPhysics, SimRobotConfig

CALIBRATE_STAGE = "calibrate"
ROBOT_CONFIGS = PROJECT_ROOT / "conf" / "robot"
# SimPhysics field -> its type as declared ("float", "list[float]", "int", "dict[str, Any]")
PHYSICS_TYPES = {f.name: str(f.type) for f in dataclasses.fields(SimPhysics)}


def load_physics(source: str, artifact_dir: str | Path, setting: str = "robot.physics_from"
                 ) -> dict[str, Any]:
    """The fitted SimPhysics values of a calibrate artifact given by key or folder; an error
    naming ``setting`` where there is none."""
    path = Path(source)
    if not (path / "physics.json").is_file():
        found = ArtifactStore(artifact_dir).find(CALIBRATE_STAGE, str(source))
        if found is None:
            raise MissingArtifactError(
                f"{setting}={source!r}: neither a folder holding physics.json nor the key of a "
                f"calibrate artifact under {Path(artifact_dir) / CALIBRATE_STAGE}")
        path = found.path
    return json.loads((path / "physics.json").read_text())["physics"]


def robot_config_physics(name: str) -> dict[str, Any] | None:
    """The physics of the simulated robot config ``conf/robot/<name>.yaml`` over the
    :class:`~pipeline.schemas.SimPhysics` defaults, without its per-session spread; None where
    there is no such config. An error where the config has no physics (not a simulated arm)."""
    path = ROBOT_CONFIGS / f"{name}.yaml"
    if "/" in name or not path.is_file():
        return None
    physics = (yaml.safe_load(path.read_text()) or {}).get("physics")
    if physics is None:
        raise ConfigError(f"conf/robot/{name}.yaml has no physics: a twin needs a simulated "
                          f"robot config (e.g. sim, sim_sorolex) or a calibrate artifact")
    return _nominal(physics, f"conf/robot/{name}.yaml physics")


def _typed(value: Any, kind: str, what: str) -> Any:
    """``value`` as a SimPhysics field of type ``kind`` holds it (numbers as floats where the
    field is a float, as the structured config makes them); an error naming ``what``."""
    try:
        if kind == "float":
            return float(value)
        if kind == "int":
            if float(value) != int(value):
                raise ValueError(f"{value!r} is not a whole number")
            return int(value)
        if kind == "list[float]":
            return [float(v) for v in value]
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{what}: expected {kind}, got {value!r} ({err})") from err
    return value


def _nominal(values: dict[str, Any], what: str) -> dict[str, Any]:
    """``values`` (SimPhysics fields) over the schema's defaults, without a per-session spread;
    an error naming ``what`` for a field that SimPhysics lacks or a value of the wrong type."""
    unknown = sorted(set(values) - set(PHYSICS_TYPES))
    if unknown:
        raise ConfigError(f"{what}: {unknown} are not SimPhysics fields of this version")
    merged = {**dataclasses.asdict(SimPhysics()), **values}
    merged = {k: _typed(v, PHYSICS_TYPES[k], f"{what}.{k}") for k, v in merged.items()}
    merged["session_std"] = {}
    return merged


def twin_physics(entry: str, artifact_dir: str | Path, setting: str = "evaluation.twins"
                 ) -> dict[str, Any]:
    """SimPhysics values of a twin: a simulated robot config's name, or a calibrate artifact's
    key or folder (the fitted values over the SimPhysics defaults)."""
    from_config = robot_config_physics(str(entry))
    if from_config is not None:
        return from_config
    fitted = load_physics(str(entry), artifact_dir, setting=setting)
    unknown = sorted(set(fitted) - set(PHYSICS_TYPES))
    if unknown:
        raise ConfigError(f"{setting}: {entry!r} has parameters {unknown} that are not "
                          f"SimPhysics fields of this version")
    return _nominal(fitted, f"{setting}: {entry!r}")


def twin_sim_params(physics: dict[str, Any]) -> Any:
    """The simulator's :class:`~pipeline.arm.sim_arm.SimParams` of ``physics`` (SimPhysics
    values), integrated at the default motion-capture rate
    (:class:`~pipeline.schemas.MocapConfig`)."""
    from pipeline.arm import sim_arm  # JAX only where a twin is simulated, not to find one

    robot = SimRobotConfig(physics=SimPhysics(**physics), mocap=MocapConfig())
    return sim_arm.SimParams.from_config(robot)
