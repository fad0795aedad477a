"""Keyed random streams: a child of a SeedSequence named by integer keys.

``SeedSequence.spawn`` numbers its children in the order they are asked for; a keyed child
is the same whatever else was drawn or spawned, so that an error source, a slice or the
judge keeps its stream when another source is switched off (the error budget's pairs).
"""

from __future__ import annotations

import numpy as np

__all__ = ["keyed_seed", "seed_sequence_of"]


def keyed_seed(seq: np.random.SeedSequence, *key: int) -> np.random.SeedSequence:
    """The child of ``seq`` at ``key`` (its spawn key extended by ``key``)."""
    return np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, *map(int, key)),
                                  pool_size=seq.pool_size)


def seed_sequence_of(rng) -> np.random.SeedSequence:
    """The SeedSequence behind ``rng`` (a Generator, a seed or None)."""
    seq = getattr(np.random.default_rng(rng).bit_generator, "seed_seq", None)
    if not isinstance(seq, np.random.SeedSequence):
        raise ValueError("rng: expected a numpy Generator made from a seed or SeedSequence "
                         f"(its bit generator has no SeedSequence: {rng!r})")
    return seq
