"""Train/test split by run, sliding windows over runs, and batch sampling of windows.

Runs are concatenated along time into one array per signal; a window is the start offset of
``length`` consecutive rows that lie inside a single run. Batches are drawn as a pure function of
``(key, step)``, so a resumed training sees exactly the batches an uninterrupted one would.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

ORDERS = ("permuted", "sequential")


def split_runs(
    run_ids: Sequence[str], train_fraction: float, seed: int
) -> tuple[list[str], list[str]]:
    """Deterministic split of run ids into (train, test), both returned sorted.

    The ids are sorted first, so the split does not depend on the order they were listed in.
    ``round(train_fraction * n)`` runs train, but at least one run is kept on each side when
    there are two or more runs and ``0 < train_fraction < 1``.
    """
    if not 0.0 <= train_fraction <= 1.0:
        raise ValueError(f"train_fraction must lie in [0, 1], got {train_fraction}")
    ids = sorted(run_ids)
    if len(set(ids)) != len(ids):
        raise ValueError(f"duplicate run ids: {ids}")
    num_train = round(train_fraction * len(ids))
    if len(ids) >= 2 and 0.0 < train_fraction < 1.0:
        num_train = min(max(num_train, 1), len(ids) - 1)
    order = np.random.default_rng(seed).permutation(len(ids))
    train = sorted(ids[i] for i in order[:num_train])
    test = sorted(ids[i] for i in order[num_train:])
    return train, test


class Windows(NamedTuple):
    """Sliding windows over concatenated runs.

    starts: int64 [N] offset of each window's first row in the concatenation.
    run_index: int64 [N] which run each window lies in.
    offset_in_run: int64 [N] the window's first row within its run.
    length: rows per window.
    """

    starts: np.ndarray
    run_index: np.ndarray
    offset_in_run: np.ndarray
    length: int


def make_windows(run_lengths: Sequence[int], length: int, stride: int) -> Windows:
    """Windows ``[s, s + length)`` with ``s = 0, stride, 2 * stride, ...`` inside every run.

    A run shorter than ``length`` contributes no window. Order: by run, then by start.
    """
    if length < 1 or stride < 1:
        raise ValueError(f"length and stride must be >= 1, got {length}, {stride}")
    run_offsets = np.concatenate([[0], np.cumsum(run_lengths)[:-1]]).astype(np.int64)
    starts, run_index, offset_in_run = [], [], []
    for i, (run_offset, run_length) in enumerate(zip(run_offsets, run_lengths)):
        local = np.arange(0, run_length - length + 1, stride, dtype=np.int64)
        starts.append(run_offset + local)
        run_index.append(np.full(local.shape, i, np.int64))
        offset_in_run.append(local)
    return Windows(
        starts=np.concatenate(starts) if starts else np.zeros(0, np.int64),
        run_index=np.concatenate(run_index) if run_index else np.zeros(0, np.int64),
        offset_in_run=np.concatenate(offset_in_run) if offset_in_run else np.zeros(0, np.int64),
        length=int(length),
    )


def weighted_starts(windows: Windows, run_weights: Sequence[float]) -> np.ndarray:
    """The window starts with each run's windows drawn ``run_weights[i]`` times as often: every
    window of run ``i`` ``floor(w)`` times and, for the fraction ``f = w - floor(w)``, the
    windows at ``floor(k / f)``, ``k = 0, 1, ...`` of the run once more (evenly spread).
    A weight of 0 drops the run; weights must be finite and >= 0."""
    weights = np.asarray(run_weights, np.float64)
    if not (np.all(np.isfinite(weights)) and np.all(weights >= 0)):
        raise ValueError(f"run weights must be finite and >= 0, got {weights.tolist()}")
    starts = []
    for run, weight in enumerate(weights):
        own = windows.starts[windows.run_index == run]
        whole, fraction = divmod(float(weight), 1.0)
        starts += [own] * int(whole)
        if fraction > 0 and len(own):
            picked = np.unique(np.floor(np.arange(0, len(own) * fraction) / fraction))
            starts.append(own[picked.astype(np.int64)])
    return np.concatenate(starts) if starts else np.zeros(0, np.int64)


def batches_per_epoch(num_windows: int, batch_size: int) -> int:
    """Full batches in one pass over the windows (the last partial batch is dropped)."""
    return max(1, num_windows // batch_size)


def sample_batch(
    key: jax.Array,
    step: jax.Array,
    num_windows: int | jax.Array,
    batch_size: int,
    order: str,
    capacity: int | None = None,
) -> jax.Array:
    """int32 [batch_size] window indices of training step ``step`` (jit-friendly).

    ``permuted``: epoch ``e = step // batches_per_epoch`` walks through the permutation drawn
    from ``fold_in(key, e)``, a fresh key per epoch. ``sequential``: every epoch walks through the
    windows in time order (``key`` unused). With fewer windows than ``batch_size``, indices wrap.

    ``capacity``: the length of a padded window list of which the first ``num_windows`` entries
    are real (``num_windows`` may then be a traced scalar, e.g. one per vmapped fold; default
    ``num_windows``). The permutation sorts 31 random bits per slot with the padding last, and
    the bits of slot ``i`` do not depend on ``capacity``, so a padded list draws exactly the
    batches of the unpadded one.
    """
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    if capacity is None:
        capacity = int(num_windows)
    num_windows = jnp.asarray(num_windows, jnp.int32)
    per_epoch = jnp.maximum(1, num_windows // batch_size)
    epoch, position = jnp.divmod(jnp.asarray(step, jnp.int32), per_epoch)
    positions = (position * batch_size + jnp.arange(batch_size)) % num_windows
    if order == "sequential":
        return positions.astype(jnp.int32)
    bits = jax.random.bits(jax.random.fold_in(key, epoch), (capacity,), jnp.uint32) >> 1
    sort_keys = jnp.where(jnp.arange(capacity) < num_windows, bits, jnp.uint32(1 << 31))
    permutation = jnp.argsort(sort_keys, stable=True)
    return permutation[positions].astype(jnp.int32)


def gather_windows(series: jax.Array, starts: jax.Array, length: int) -> jax.Array:
    """Rows ``series[s : s + length]`` for every start: [N, D], [B] -> [B, length, D]."""
    chex.assert_rank(series, 2)
    chex.assert_rank(starts, 1)
    return series[starts[:, None] + jnp.arange(length)[None, :]]
