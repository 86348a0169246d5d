"""The configuration reference, generated from the schemas (``pipeline/schemas/``) and the
config groups (``conf/``) when the site is built: an MkDocs hook adds ``reference/configuration.md``
to the site, so there is no hand-kept copy to drift.

For every group: its options (the YAML files) and what each sets over the schema; for every
setting: its type, default, unit, description (the comment beside the field, or the docstring of
its schema) and the validation rules that name it (the messages of ``pipeline.validation``'s checks and the schemas' own).

``python docs/hooks/config_reference.py`` prints the page.
"""

from __future__ import annotations

import ast
import dataclasses
import enum
import inspect
import re
import sys
import typing
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
PAGE = "reference/configuration.md"
# the unit a setting's name ends with, where its comment does not give one in brackets
SUFFIX_UNITS = {"_s": "s", "_m": "m", "_mm": "mm", "_kpa": "kPa", "_hz": "Hz", "_deg": "deg",
                "_m_per_s": "m/s", "_per_kpa": "1/kPa", "_gb": "GB", "_min": "min"}
NAME_UNITS = {"p_min": "kPa", "p_max": "kPa", "sum_max": "kPa", "preload": "kPa",
              "noise_std": "kPa", "time_scale": "arm s per wall s"}


def _import_config():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    import pipeline.config as config

    config.register_configs()
    return config


def _field_comments(cls: type) -> dict[str, str]:
    """The comment on each field of ``cls``: the one at the end of its line and the comment
    lines right above it, joined."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    comments, above = {}, []
    for line in lines[1:]:
        stripped = line.strip()
        if stripped.startswith("#"):
            above.append(stripped.lstrip("# ").strip())
            continue
        match = re.match(r"\s+(\w+)\s*:\s*[^=]+?(?:=.*?)?(?:#\s*(.*))?$", line)
        if match and not stripped.startswith(("def ", "@", "return", '"""')):
            text = " ".join([*above, match.group(2) or ""]).strip()
            if text:
                comments[match.group(1)] = text
        above = []
    return comments


def _unit(name: str, comment: str) -> str:
    bracket = re.search(r"\[([^\]]+)\]", comment)
    if bracket:
        return bracket.group(1)
    if name in NAME_UNITS:
        return NAME_UNITS[name]
    for suffix, unit in sorted(SUFFIX_UNITS.items(), key=lambda kv: -len(kv[0])):
        if name.endswith(suffix):
            return unit
    return ""


def _default(field: dataclasses.Field) -> Any:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return field.default_factory()  # type: ignore[misc]
    return None


def _show(value: Any) -> str:
    if isinstance(value, enum.Enum):
        value = value.value
    if value is None:
        return "null"
    if isinstance(value, str) and value == "???":
        return "(required)"
    if isinstance(value, bool):
        return str(value).lower()
    text = str(value) if not isinstance(value, str) else value
    return text if text else '""'


def _type_name(annotation: Any) -> str:
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__",
                                                                   str(annotation))
    return text.replace("typing.", "")


def _resolved_hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # a forward reference the module does not resolve: the
        # annotations are then shown as written
        return {}


def _choices(hint: Any) -> str:
    for candidate in (hint, *typing.get_args(hint)):
        if isinstance(candidate, type) and issubclass(candidate, enum.Enum):
            return " \\| ".join(f"`{m.value}`" for m in candidate)
    return ""


def schema_rows(cls: type, prefix: str) -> list[dict[str, str]]:
    """One row per setting of dataclass ``cls`` (nested dataclasses flattened), named
    ``prefix.field``."""
    rows = []
    comments = _field_comments(cls)
    hints = _resolved_hints(cls)
    for field in dataclasses.fields(cls):
        name = f"{prefix}.{field.name}" if prefix else field.name
        hint = hints.get(field.name, field.type)
        default = _default(field)
        nested = hint if dataclasses.is_dataclass(hint) else (
            type(default) if dataclasses.is_dataclass(default) else None)
        if nested is not None:
            rows += schema_rows(nested, name)
            continue
        comment = comments.get(field.name, "")
        optional = [a for a in typing.get_args(hint) if dataclasses.is_dataclass(a)]
        if optional:  # a section that may be left out (null), with settings of its own
            rows.append({"key": name, "type": _type_name(field.type), "default": _show(default),
                         "unit": "", "description": comment or (
                             f"optional ({optional[0].__name__}, below); null: none")})
            rows += schema_rows(optional[0], name)
            continue
        choices = _choices(hint)
        rows.append({"key": name, "type": _type_name(field.type), "default": _show(default),
                     "unit": _unit(field.name, comment),
                     "description": comment + (f" One of {choices}." if choices else "")})
    return rows


def validation_rules(*sources: Path) -> dict[str, list[str]]:
    """The messages of every ``ConfigError``/``ValueError`` raised in ``sources``, by the setting
    they name first (``group.key`` or ``key``); f-string values shown as ``…``."""
    rules: dict[str, list[str]] = {}
    nodes = (node for source in sources for node in ast.walk(ast.parse(source.read_text())))
    for node in nodes:
        if not (isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call)
                and getattr(node.exc.func, "id", "") in ("ConfigError", "ValueError")
                and node.exc.args):
            continue
        text = re.sub(r"\s+", " ", _literal(node.exc.args[0])).strip()
        match = re.match(r"[`']?([a-z_][a-z0-9_]*(?:\.[a-z_][a-z0-9_]*)*)(?=[=:` ])", text)
        rules.setdefault(match.group(1) if match else "", []).append(text)
    return rules


def _literal(node: ast.AST) -> str:
    if isinstance(node, ast.Constant):
        return str(node.value)
    if isinstance(node, ast.JoinedStr):
        return "".join(str(v.value) if isinstance(v, ast.Constant) else "…" for v in node.values)
    if isinstance(node, ast.BinOp):
        return _literal(node.left) + _literal(node.right)
    return "…"


def _yaml_settings(path: Path) -> tuple[list[str], dict[str, Any]]:
    import yaml

    data = yaml.safe_load(path.read_text()) or {}
    defaults = data.pop("defaults", []) or []
    return [str(d) if not isinstance(d, dict) else ", ".join(f"{k}: {v}" for k, v in d.items())
            for d in defaults], data


def _flatten(data: Any, prefix: str = "") -> list[tuple[str, Any]]:
    if isinstance(data, dict) and data:
        out = []
        for key, value in data.items():
            out += _flatten(value, f"{prefix}.{key}" if prefix else str(key))
        return out
    return [(prefix, data)]


def _first_comment(path: Path) -> str:
    lines = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        text = line.lstrip("#").strip()
        if text.startswith("@package"):
            continue
        lines.append(text)
    return " ".join(lines)


def _table(rows: list[dict[str, str]], rules: dict[str, list[str]]) -> list[str]:
    out = ["| setting | type | default | unit | description | validation |",
           "| --- | --- | --- | --- | --- | --- |"]
    for row in rows:
        checks = "<br>".join(rules.get(row["key"], []))
        cells = [f"`{row['key']}`", row["type"], f"`{row['default']}`", row["unit"],
                 row["description"], checks]
        out.append("| " + " | ".join(c.replace("|", "\\|").replace("\\\\|", "\\|")
                                     for c in cells) + " |")
    return out


def _schema_of(config: Any, group: str, option_file: Path) -> type | None:
    """The dataclass a group option extends (the ``base_*`` entry of its defaults list,
    following other options of the group it names)."""
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    defaults, _ = _yaml_settings(option_file)
    store = ConfigStore.instance().repo
    for entry in defaults:
        node = store
        for part in [*group.split("/"), f"{entry}.yaml"]:
            node = node.get(part, {}) if isinstance(node, dict) else {}
        if hasattr(node, "node"):
            return OmegaConf.get_type(node.node)
        sibling = option_file.parent / f"{entry}.yaml"
        if sibling.is_file() and sibling != option_file:
            return _schema_of(config, group, sibling)
    return None


def _group_rows(config: Any, conf: Path, group: str) -> list[dict[str, str]]:
    schemas = {_schema_of(config, group, option) for option in (conf / group).glob("*.yaml")}
    return [row for schema in schemas if schema is not None
            for row in schema_rows(schema, group)]


def reference_markdown() -> str:
    """The configuration reference page (Markdown)."""
    config = _import_config()
    conf = ROOT / "conf"
    rules = validation_rules(ROOT / "pipeline" / "validation.py",
                             *sorted((ROOT / "pipeline" / "schemas").glob("*.py")))
    lines = ["# Configuration reference", "",
             "Generated from the schemas in `pipeline/schemas/` and the options in `conf/` each "
             "time the site is built (`docs/hooks/config_reference.py`). Set any value on the "
             "command line (`python -m pipeline model.hidden=64`), pick an option of a group "
             "(`robot=sorolex_csv`), or sweep (`-m agent=ppo_ff,ppo_rnn`). A mistyped key fails "
             "at composition with the close matches; `python -m pipeline --cfg job` prints the "
             "whole composed config.", "",
             "Units: pressures in kPa, positions in metres, times in seconds, rates in Hz, unless "
             "a setting's name or description says otherwise. The *validation* column lists the "
             "messages of the checks run before any work (`pipeline.validation.validate_config` and "
             "the schemas' own checks); `…` stands for the value in the message.", ""]
    lines += ["## Top-level settings", ""]
    top = [r for r in schema_rows(config.Config, "") if "." not in r["key"]
           and r["default"] != "(required)"]
    lines += [*_table(top, rules), ""]
    groups = sorted(p.name for p in conf.iterdir() if p.is_dir() and p.name != "hydra")
    for group in groups:
        options = sorted((conf / group).glob("*.yaml"))
        lines += [f"## `{group}`", ""]
        schemas: dict[type, list[str]] = {}
        for option in options:
            schema = _schema_of(config, group, option)
            if schema is not None:
                schemas.setdefault(schema, []).append(option.stem)
        lines += ["Options:", ""]
        for option in options:
            defaults, settings = _yaml_settings(option)
            about = _first_comment(option)
            flat = [(k, v) for k, v in _flatten(settings) if k]
            sets = ", ".join(f"`{k}={_show(v)}`" for k, v in flat[:40])
            if len(flat) > 40:
                sets += f" and {len(flat) - 40} more"
            base = [d for d in defaults if d not in ("_self_",)]
            lines.append(f"- **`{group}={option.stem}`**"
                         + (f" (extends {', '.join(f'`{b}`' for b in base)})" if base else "")
                         + (f": {about}" if about else "")
                         + (f" Sets: {sets}." if sets else ""))
        lines.append("")
        for schema, names in schemas.items():
            doc = inspect.getdoc(schema) or ""
            lines += [f"### `{group}` settings: `{schema.__name__}` "
                      f"({', '.join(f'`{n}`' for n in names)})", ""]
            if doc:
                lines += [" ".join(doc.split()), ""]
            lines += [*_table(schema_rows(schema, group), rules), ""]
    shown = {r["key"] for r in top} | {row["key"] for g in groups for row in _group_rows(
        config, conf, g)}
    spanning = [text for key, texts in sorted(rules.items()) if key not in shown
                for text in texts]
    lines += ["## Checks that span settings", "",
              "The other messages of the checks, where a rule covers several settings (`…` in "
              "a setting's name: each of a family, such as the robot's durations):", ""]
    lines += [f"- {text}" for text in spanning] + [""]
    launchers = sorted((conf / "hydra" / "launcher").glob("*.yaml"))
    lines += ["## `hydra/launcher`", "",
              "How a sweep (`-m`) runs its jobs; each option extends its plugin's schema "
              "(`base_<option>`).", ""]
    for option in launchers:
        _, settings = _yaml_settings(option)
        sets = ", ".join(f"`hydra.launcher.{k}={_show(v)}`" for k, v in _flatten(settings) if k)
        lines.append(f"- **`hydra/launcher={option.stem}`**: {_first_comment(option)} "
                     f"Sets: {sets}.")
    lines.append("")
    return "\n".join(lines)


def on_files(files, config):  # MkDocs hook: the page joins the site's files
    from mkdocs.structure.files import File

    files.append(File.generated(config, PAGE, content=reference_markdown()))
    return files


if __name__ == "__main__":
    print(reference_markdown())
