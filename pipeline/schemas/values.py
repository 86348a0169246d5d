"""What the schemas share: the missing-value marker and reading a dataclass's values from a
mapping; and the error a config that cannot run raises.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

# OmegaConf's marker of a mandatory value (``omegaconf.MISSING``), without importing it
MISSING: Any = "???"


class ConfigError(ValueError):
    """A composed config that cannot run: the message names the setting and its value."""



def dataclass_values(cls: type, config: Any, what: str,
                     overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Field values for dataclass ``cls`` read from a dataclass, a mapping or an OmegaConf node
    (plus ``overrides``); unknown keys fail, naming ``what`` ("agent", "model")."""
    if dataclasses.is_dataclass(config):
        values = dataclasses.asdict(config)
    elif isinstance(config, Mapping) or hasattr(config, "items"):
        values = dict(config.items())
    else:
        raise TypeError(f"cannot read a{'n' if what[0] in 'aeiou' else ''} {what} config from "
                        f"{type(config).__name__}")
    values.update(overrides or {})
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown {what} config keys {unknown}; known: {sorted(known)}")
    return values


def frozen_twin(schema: type, name: str) -> type:
    """A frozen (hashable) dataclass with ``schema``'s fields and defaults, lists as tuples: the
    schema in the form runtime code can pass to ``jax.jit`` as a static argument. Derived, so
    the schema stays the only place a field is declared."""
    fields = []
    for f in dataclasses.fields(schema):
        default = (f.default_factory() if f.default_factory is not dataclasses.MISSING
                   else f.default)
        if isinstance(default, list):
            default = tuple(default)
        fields.append((f.name, Any, dataclasses.field(default=default)))
    return dataclasses.make_dataclass(name, fields, frozen=True)
