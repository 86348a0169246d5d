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


def quiet_xla_log() -> None:
    """XLA's C++ log at ``TF_CPP_MIN_LOG_LEVEL`` (3, FATAL only, unless the caller set it),
    applied to the running jaxlib; imports JAX.

    On AVX-512 CPUs every program loaded from the compilation cache logs two spurious errors
    (``cpu_aot_loader.cc``: "machine type doesn't match", for tuning features of the same
    machine, jax-ml/jax#38445) and a warning (``pjrt_executable.cc``: "Assume version
    compatibility"). The variable alone hides them when a script sets it before it imports JAX,
    but not under the pipeline's entry point (measured with jaxlib 0.9.2: the lines come back
    whenever JAX is first imported inside the Hydra task), so the level is also set through
    jaxlib's own setter (what ``jax_logging_level`` uses) once JAX is loaded. Errors that matter
    reach Python as exceptions; ``TF_CPP_MIN_LOG_LEVEL=0`` shows everything.
    """
    level = int(os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3"))
    import jax  # noqa: F401  (loads jaxlib)

    try:
        from jax._src.lib import utils
    except ImportError:  # a jaxlib without the setter: the variable is all there is
        log.debug("jaxlib has no absl_set_min_log_level: TF_CPP_MIN_LOG_LEVEL only")
        return
    utils.absl_set_min_log_level(level)
