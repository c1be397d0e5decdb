"""Deterministic child seeds that never mutate the caller's SeedSequence.

``SeedSequence.spawn`` counts how many children it has handed out, so calling it twice on the
caller's object gives different children. Rendering must be a pure function of
(seed_sequence, rate), so children are derived by extending the spawn key instead.
"""

from __future__ import annotations

import numpy as np

STREAM_LENS = 1
"""Stream id of the lens-drop sequence (jeon2022 drops, and physical lens drops)."""

STREAM_AIR = 2
"""Stream id of the falling-drop candidates of the physical model."""

STREAM_SPRAY = 3
"""Stream id of the tyre-spray particles of a frame."""


def check_seed_sequence(seed_sequence: object) -> np.random.SeedSequence:
    """Return ``seed_sequence`` if it is a ``np.random.SeedSequence``; raise TypeError otherwise."""
    if not isinstance(seed_sequence, np.random.SeedSequence):
        raise TypeError(
            "seed_sequence must be a numpy.random.SeedSequence, e.g. "
            f"np.random.SeedSequence([rain_seed, scene_seed, frame]); got {type(seed_sequence).__name__}"
        )
    return seed_sequence


def child_generator(seed_sequence: np.random.SeedSequence, *key: int) -> np.random.Generator:
    """A PCG64 generator seeded by ``seed_sequence`` with ``key`` appended to its spawn key.

    Args:
        seed_sequence: the caller's sequence (left untouched).
        key: non-negative ints naming the stream (and block) of random numbers.

    Returns:
        a fresh ``np.random.Generator``; the same arguments always give the same stream.
    """
    child = np.random.SeedSequence(
        entropy=seed_sequence.entropy,
        spawn_key=tuple(seed_sequence.spawn_key) + tuple(int(k) for k in key),
        pool_size=seed_sequence.pool_size,
    )
    return np.random.Generator(np.random.PCG64(child))
