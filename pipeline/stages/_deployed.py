"""The deployed policy of a config, for the stages that drive an arm with it (``control``,
``adapt``): its artifact and the settings that rebuild the environment it was trained in."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from pipeline import keys
from pipeline.infra.artifacts import MANIFEST, Artifact, ArtifactStore
from pipeline.keys import SPEC_VERSIONS
from pipeline.schemas import (
    ConfigError,
    EnvConfig,
    EnvName,
    PressureLimits,
    SimRobotConfig,
)


def policy_artifact(cfg: Any, store: ArtifactStore) -> tuple[Artifact, ArtifactStore]:
    """The train_ppo (or adapt) artifact of ``control.policy_file``, or the train_ppo artifact of
    ``control.policy`` (by key), and the store that holds it and its lineage (that of
    ``control.policy_file``'s folder)."""
    stage, key = keys.control_policy(cfg)
    if cfg.control.policy_file:
        folder = Path(str(cfg.control.policy_file)).resolve().parent
        return Artifact(stage, key, folder), ArtifactStore(folder.parent.parent)
    hint = (f" with agent={cfg.control.policy}, on this robot's data (robot=ros2: `stage=collect` "
            f"first); or point control.policy_file at a train_ppo policy.msgpack")
    return store.require("train_ppo", key, hint=hint), store


def training_config(artifact: Artifact, store: ArtifactStore, n_valves: int
                    ) -> tuple[Any, Artifact | None, Artifact | None]:
    """``(config, fit_model artifact, align artifact)`` that rebuild the artifact's environment
    with :func:`~pipeline.stages._environment.config_environment`: the env, robot rate and limits,
    and model rate it was trained with (the tracking task's preview included), read from its
    manifest and those of its inputs, laid over the schemas' defaults (the spec keeps what differs
    from them). An adapt artifact's
    environment is that of the policy it adapted with its calibrated model (``model.msgpack``
    and ``split.json`` in its folder) in place of the fit_model artifact."""
    if artifact.stage == "adapt":
        deployed, lineage = adapted_from(artifact, store)
        config, _, aligned = training_config(deployed, lineage, n_valves)
        return config, artifact, aligned
    manifest = artifact.manifest
    spec = manifest["spec"]
    version = spec.get("spec_version", 1)
    if version != SPEC_VERSIONS["train_ppo"]:
        raise ConfigError(f"{artifact.path}: a policy of train_ppo spec version {version}, this "
                          f"version rebuilds environments of version "
                          f"{SPEC_VERSIONS['train_ppo']}; train it anew (stage=train_ppo)")
    env_name = EnvName(spec["env"]["name"])
    if env_name is EnvName.gymnax:
        raise ValueError(f"{artifact.path}: a policy of a gymnax environment "
                         f"({spec['env'].get('gymnax_name')}) cannot drive the arm")
    env = OmegaConf.merge(OmegaConf.structured(EnvConfig), spec["env"])
    if env_name is EnvName.sim:
        robot = OmegaConf.merge(OmegaConf.structured(SimRobotConfig), spec["robot"])
        dataset = {"model_hz": spec["model_hz"]}
        return OmegaConf.create({"env": env, "robot": robot, "dataset": dataset}), None, None
    model = store.require("fit_model", manifest["inputs"]["fit_model"])
    aligned = store.require("align", model.manifest["inputs"]["align"])
    dataset = model.manifest["spec"]["dataset"]
    robot = {"control_hz": spec["control_hz"], "n_valves": n_valves,
             "limits": OmegaConf.merge(OmegaConf.structured(PressureLimits), spec["limits"])}
    config = OmegaConf.create({"env": env, "robot": robot,
                               "dataset": {"model_hz": dataset["model_hz"],
                                           "model_grid": dataset["model_grid"]}})
    return config, model, aligned


def adapted_from(artifact: Artifact, store: ArtifactStore) -> tuple[Artifact, ArtifactStore]:
    """The train_ppo artifact an adapt artifact adapted, and the store of its lineage: in
    ``store`` by key, else where adapt found it (``deployed_path`` in its summary: a policy of
    another artifact store, named by ``control.policy_file``)."""
    key = artifact.manifest["inputs"]["train_ppo"]
    found = store.find("train_ppo", key)
    if found is not None:
        return found, store
    recorded = artifact.manifest.get("summary", {}).get("deployed_path")
    if recorded:
        candidate = Artifact("train_ppo", key, Path(recorded))
        if candidate.file(MANIFEST).is_file() and candidate.manifest.get("key") == key:
            return candidate, ArtifactStore(Path(recorded).parent.parent)
    return store.require("train_ppo", key, hint=f" (the policy {artifact.path} adapted)"), store

