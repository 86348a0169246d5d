"""The CPU's cores (or a machine's GPUs) as JAX devices, and batches split over them.

XLA runs a program on one CPU device in one thread for the small operations this project is
made of (PPO's networks, the learned model): a 2-core machine trained at the speed of one core.
Asked for one CPU device per core (``cpu_devices``, JAX's ``jax_num_cpu_devices``), XLA runs a
program whose batch axis is split over the devices as one part per device, in parallel: the
PPO seeds (``pipeline.rl.ppo.train_seeds``) and the evaluation's episodes
(``pipeline.evaluation.closed_loop``). Each part computes what it computed in the whole batch,
to float rounding: XLA may order a sum differently for a smaller batch, and over a long PPO
training such last-bit differences grow into a different draw of the same seeds' noise
(``tests/test_devices.py``; ``docs/results/PPO_RESULTS.md``).

The split (:func:`batch_split`) is over ``jax.local_devices()``, the devices of JAX's default
backend: one CPU device per core on a CPU-only machine, the GPUs on a machine with JAX's CUDA
wheels (``pip install -e ".[cuda]"``), where the CPU device count no longer matters for these
programs. A batch is split over the most devices that divide it evenly (:func:`split_count`):
20 seeds over 10 of 16 CPU devices (2 seeds each), over 5 of 8 GPUs (4 each), over all 4 of 4
GPUs (5 each); on one GPU, as on one CPU device, it is not split.

JAX is not imported at module import: the entry point sets the device count before JAX starts.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any, NamedTuple

from pipeline.schemas import ConfigError

log = logging.getLogger(__name__)

AXIS = "batch"


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def configure_cpu_devices(count: int | None) -> int:
    """Ask JAX for ``count`` CPU devices (None: the caller's ``JAX_NUM_CPU_DEVICES`` where set,
    else one per usable core) before it starts its backends; returns the count asked for. Where
    JAX has already started them (a library use inside a running program), the count stays what
    it is, and that is logged."""
    if count is None:
        count = int(os.environ.get("JAX_NUM_CPU_DEVICES") or usable_cores())
    count = int(count)
    if count < 1:
        raise ConfigError(f"cpu_devices must be at least 1 (or null: one per core), got {count}")
    if "jax" not in sys.modules:
        os.environ["JAX_NUM_CPU_DEVICES"] = str(count)
        return count
    import jax

    try:
        jax.config.update("jax_num_cpu_devices", count)
    except RuntimeError:
        try:
            running = str(jax.local_device_count("cpu"))
        except RuntimeError:  # no CPU backend (JAX_PLATFORMS=cuda)
            running = "none"
        log.debug("JAX's backends are running: the CPU device count stays %s", running)
    return count


class BatchSplit(NamedTuple):
    """A batch axis split evenly over ``mesh``'s devices."""

    mesh: Any  # jax.sharding.Mesh, one axis named AXIS

    def sharding(self, axis: int = 0) -> Any:
        """Arrays split along ``axis`` (the batch axis), whole along the others."""
        from jax.sharding import NamedSharding, PartitionSpec

        return NamedSharding(self.mesh, PartitionSpec(*([None] * axis), AXIS))

    def replicated(self) -> Any:
        from jax.sharding import NamedSharding, PartitionSpec

        return NamedSharding(self.mesh, PartitionSpec())

    def put(self, tree: Any, axis: int | None = 0) -> Any:
        """``tree``'s arrays on the mesh: split along ``axis``, or whole on every device
        (``axis=None``)."""
        import jax

        return jax.device_put(tree, self.replicated() if axis is None else self.sharding(axis))


def split_count(size: int, devices: int) -> int:
    """Over how many of ``devices`` devices a batch of ``size`` is split: the most that divide
    it evenly (1: not split). 20 seeds: 10 of 16 devices, 5 of 8, 4 of 4, 1 of 3."""
    return max(n for n in range(1, devices + 1) if size % n == 0)


def batch_split(size: int) -> BatchSplit | None:
    """The split of a batch of ``size`` over the most local devices of JAX's default backend
    (the CPU devices, or the GPUs) that divide it evenly (:func:`split_count`); None where that
    is one device (nothing to split)."""
    import jax
    import numpy as np
    from jax.sharding import Mesh

    devices = jax.local_devices()  # the default backend's: CPU devices or GPUs
    count = split_count(size, len(devices))
    if count == 1:
        return None
    return BatchSplit(Mesh(np.asarray(devices[:count]), (AXIS,)))
