"""JAX's persistent compilation cache: compiled programs are kept on disk and reused by later
processes (runs, sweep jobs, tests) instead of compiling the same program again.

JAX writes each entry under a content hash of the program and its compile options, so parallel
sweep jobs may share one folder: the same program gives the same entry, written whole.

JAX itself is not imported here: a process that never compiles (the guard, which only checks
commands) starts without loading it.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def use_compilation_cache(folder: str | Path | None, min_compile_seconds: float = 0.5) -> None:
    """Cache every program that takes at least ``min_compile_seconds`` to compile in
    ``folder`` (created if missing); None leaves the cache off."""
    if folder is None:
        return
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    settings = {"jax_compilation_cache_dir": str(folder),
                "jax_persistent_cache_min_compile_time_secs": float(min_compile_seconds),
                "jax_persistent_cache_min_entry_size_bytes": 0}
    # JAX reads each option from its upper-case environment variable when it is imported (later
    # in this process, or in a child); a JAX already imported is told directly
    os.environ.update({name.upper(): str(value) for name, value in settings.items()})
    if "jax" in sys.modules:
        for name, value in settings.items():
            sys.modules["jax"].config.update(name, value)
    log.debug("JAX compilation cache in %s", folder)
