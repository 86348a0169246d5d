"""The command line around Hydra: the dynamic parts of ``--help`` and a clear message for a
mistyped config key.

- :func:`register_help` registers the ``${sorolearn_stages:}`` and ``${sorolearn_groups:}``
  resolvers that ``conf/hydra/help/sorolearn.yaml`` (the ``--help`` page) uses: the stages with the
  first line of their module's docstring, and the config groups with their options as files in
  ``conf/`` (the ``base_*`` schemas registered in Hydra's ConfigStore are not options to choose).
- :func:`unknown_key_message`: for an override of a key that is not in the composed config,
  Hydra suggests appending it (``+key=value``), which would only hide the typo. This names the
  key as unknown and lists the close matches from the schema instead.
"""

from __future__ import annotations

import ast
import difflib
import importlib.util
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pipeline.config import PROJECT_ROOT

CONF_DIR = PROJECT_ROOT / "conf"


# ---------------------------------------------------------------------------------------------
# --help
# ---------------------------------------------------------------------------------------------
def stage_lines(stages: Mapping[Any, str]) -> str:
    """One line per stage: its name and the first line of its module's docstring (read from the
    source, so that ``--help`` imports no stage and no JAX)."""
    rows = []
    for stage, target in stages.items():
        name = getattr(stage, "value", stage)
        spec = importlib.util.find_spec(target.split(":")[0])
        doc = ast.get_docstring(ast.parse(Path(spec.origin).read_text())) if spec else None
        line = (doc or "").splitlines()[0] if doc else ""
        line = line.split(": ", 1)[-1].split(" (")[0].rstrip(".").replace("``", "")
        rows.append(f"  {name:<10} {line}")
    return "\n".join(rows)


def group_lines(conf_dir: Path = CONF_DIR) -> str:
    """``group: option, option`` for every config group in ``conf_dir`` (and the launchers);
    the groups whose one option is ``default`` on one line of their own (their settings are
    set key by key)."""
    rows, defaults = [], []
    groups = sorted(p for p in conf_dir.iterdir() if p.is_dir() and p.name != "hydra")
    for folder in [*groups, conf_dir / "hydra" / "launcher"]:
        options = sorted(p.stem for p in folder.glob("*.yaml") if not p.stem.startswith("base_"))
        name = folder.relative_to(conf_dir).as_posix()
        if options == ["default"]:
            defaults.append(name)
        elif options:
            rows.append(f"  {name + ':':<15} {', '.join(options)}")
    if defaults:
        rows.insert(0, f"  {'default only:':<15} {', '.join(defaults)}")
    return "\n".join(rows)


def register_help(stages: Mapping[Any, str]) -> None:
    """Register the resolvers of the ``--help`` template (see the module docstring)."""
    OmegaConf.register_new_resolver("sorolearn_stages", lambda: stage_lines(stages), replace=True)
    OmegaConf.register_new_resolver("sorolearn_groups", group_lines, replace=True)


def dry_run_flag(arguments: Sequence[str]) -> list[str]:
    """The command line with ``--dry-run`` (or ``--plan``) replaced by ``dry_run=true``."""
    flags = ("--dry-run", "--plan")
    rest = [argument for argument in arguments if argument not in flags]
    return [*rest, "dry_run=true"] if len(rest) < len(arguments) else rest


# ---------------------------------------------------------------------------------------------
# unknown keys
# ---------------------------------------------------------------------------------------------
def _is_group(key: str, conf_dir: Path) -> bool:
    return (conf_dir / key).is_dir() or key.startswith("hydra/")


def _close(word: str, candidates: Sequence[str]) -> list[str]:
    return difflib.get_close_matches(word, list(candidates), n=3, cutoff=0.6)


def _exists(node: Any, key: str) -> bool:
    for part in key.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            return False
        node = node._get_node(part)
    return True


def missing_key(cfg: DictConfig, key: str) -> str | None:
    """A message naming ``key`` as unknown in ``cfg`` with its close matches, or None if the key
    is there (or lies below a list or an open dict, where any key may be set)."""
    node: Any = cfg
    parts = key.split(".")
    for depth, part in enumerate(parts):
        if not isinstance(node, DictConfig):
            return None
        if part in node:
            if depth < len(parts) - 1:
                node = node._get_node(part)  # the child node, interpolations unresolved
            continue
        if not OmegaConf.is_struct(node):
            return None
        prefix = ".".join(parts[:depth])
        where = f"in {prefix}" if prefix else "at the top level"
        schema = OmegaConf.get_type(node)
        schema_name = (f" (schema {schema.__name__} in pipeline/schemas/)"
                       if schema is not None and schema is not dict else "")
        rest = ".".join(parts[depth + 1:])
        matches = [".".join(p for p in (prefix, m, rest) if p) for m in _close(part, node.keys())
                   if not rest or _exists(node._get_node(m), rest)]
        hint = (f"did you mean {' or '.join(matches)}?" if matches
                else f"the keys there are: {', '.join(map(str, node.keys()))}.")
        return (f"Unknown config key '{key}': there is no '{part}' {where}{schema_name}; "
                f"{hint} (`python -m pipeline --cfg job` shows the whole config.)")
    return None


def unknown_key_message(argv: Sequence[str], conf_dir: Path = CONF_DIR,
                        config_name: str = "config") -> str | None:
    """The message for the first override in ``argv`` (a command line) that sets a key the
    composed config does not have; None when every key is known.

    Only plain ``key=value`` overrides are checked (``+``, ``++`` and ``~`` say what they mean;
    ``hydra.*`` keys are Hydra's). The config is composed with the command's group choices (the
    first option of a sweep); whatever fails there (a wrong option, a syntax error) is left to
    Hydra's own message.
    """
    from hydra import compose, initialize_config_dir
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    args, _ = get_args_parser().parse_known_args(list(argv))
    try:
        overrides = OverridesParser.create().parse_overrides(args.overrides)
    except HydraException:
        return None  # a syntax error: Hydra says where
    groups, keys = [], []
    for override in overrides:
        if override.is_add() or override.is_force_add() or override.is_delete():
            continue
        name = override.key_or_group
        if _is_group(name, conf_dir):
            value = (next(iter(override.sweep_string_iterator()))
                     if override.is_sweep_override() else override.get_value_element_as_str())
            groups.append(f"{override.get_key_element()}={value}")
        elif not name.startswith("hydra.") and name != "hydra":
            keys.append(name)
    if not keys:
        return None
    try:
        with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
            cfg = compose(config_name, overrides=groups)
    except HydraException:
        return None  # e.g. an unknown option of a group: Hydra's message names it
    for key in keys:
        message = missing_key(cfg, key)
        if message is not None:
            return message
    return None


def exit_on_unknown_key(argv: Sequence[str]) -> None:
    """Exit with :func:`unknown_key_message`'s message (status 1) when there is one."""
    message = unknown_key_message(argv)
    if message is not None:
        raise SystemExit(message)
