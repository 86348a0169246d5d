"""The package's layering (pyproject.toml's import-linter contracts) holds, and has no cycles."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.config import PROJECT_ROOT

importlinter = pytest.importorskip("importlinter", reason="import-linter is a dev extra")


def test_import_contracts_hold():
    # in a process of its own: import-linter configures logging, which would silence the
    # loggers of the modules already imported here
    script = Path(sys.executable).with_name("lint-imports")
    command = [str(script)] if script.is_file() else [sys.executable, "-c",
                                                     "from importlinter.cli import lint_imports_command; lint_imports_command()"]
    done = subprocess.run(command, cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


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
