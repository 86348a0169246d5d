"""The package's layering (pyproject.toml's import-linter contracts) holds, and has no cycles."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from pipeline.config import PROJECT_ROOT

importlinter = pytest.importorskip("importlinter", reason="import-linter is a dev extra")


def test_import_contracts_hold(monkeypatch):
    from importlinter import cli

    monkeypatch.chdir(PROJECT_ROOT)
    assert cli.lint_imports(config_filename=str(PROJECT_ROOT / "pyproject.toml")) == 0


def test_no_stage_is_imported_by_a_deferred_import_anywhere_in_the_package():
    """Deferred (function-level) imports escape a reader's eye; none may reach a stage."""
    offenders = []
    for path in sorted((PROJECT_ROOT / "pipeline").rglob("*.py")):
        if path.name == "__main__.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            if any(n.startswith("pipeline.stages.") for n in names) and \
                    not str(path).startswith(str(PROJECT_ROOT / "pipeline" / "stages")):
                offenders.append(f"{Path(path).relative_to(PROJECT_ROOT)}:{node.lineno}")
    assert offenders == []
