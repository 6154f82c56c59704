"""Permuted-block allocation sequences, reproducible forever from a study's secret seed.

The sequence for a stratum is a pure function of (seed, stratum, conditions, block sizes): blocks
of randomly mixed sizes, each holding every condition equally often in random order. Randomness
comes from HMAC-SHA256 in counter mode rather than a library generator, so the sequence cannot
change with a Python or NumPy upgrade and an auditor can recompute it from the seed alone.

Nothing here touches the database: :mod:`app.services.participants.enrolment` reveals one entry at a
time.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Iterator, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class SequenceEntry:
    """The ``index``-th allocation of a stratum (0-based) and the block it belongs to."""

    index: int
    block_number: int
    block_size: int
    position_in_block: int
    condition: str


class _Stream:
    """Uniform integers from HMAC-SHA256(seed, label ‖ counter): deterministic and unbiased."""

    def __init__(self, seed: bytes, label: str) -> None:
        self._seed = seed
        self._label = label.encode()
        self._counter = 0
        self._buffer = b""

    def _bytes(self, n: int) -> bytes:
        while len(self._buffer) < n:
            message = self._label + b"\x00" + self._counter.to_bytes(8, "big")
            self._buffer += hmac.new(self._seed, message, hashlib.sha256).digest()
            self._counter += 1
        out, self._buffer = self._buffer[:n], self._buffer[n:]
        return out

    def below(self, n: int) -> int:
        """A uniform integer in [0, n), by rejection sampling on 64-bit draws."""
        if n <= 0:
            raise ValueError("n must be positive")
        span = 1 << 64
        limit = span - span % n
        while True:
            draw = int.from_bytes(self._bytes(8), "big")
            if draw < limit:
                return draw % n


def _block(stream: _Stream, conditions: Sequence[str], block_sizes: Sequence[int]) -> list[str]:
    size = block_sizes[stream.below(len(block_sizes))]
    block = [condition for condition in conditions for _ in range(size // len(conditions))]
    # Fisher–Yates, drawing from the same deterministic stream.
    for i in range(len(block) - 1, 0, -1):
        j = stream.below(i + 1)
        block[i], block[j] = block[j], block[i]
    return block


def validate_scheme(conditions: Sequence[str], block_sizes: Sequence[int]) -> None:
    """Raise ValueError unless every block can hold each condition equally often."""
    if len(conditions) < 2 or len(set(conditions)) != len(conditions):
        raise ValueError("need at least two distinct conditions")
    if not block_sizes or any(size <= 0 or size % len(conditions) for size in block_sizes):
        raise ValueError(f"block sizes must be positive multiples of {len(conditions)}")


def sequence(
    seed: bytes, stratum: str, conditions: Sequence[str], block_sizes: Sequence[int]
) -> Iterator[SequenceEntry]:
    """The infinite allocation sequence of one stratum."""
    validate_scheme(conditions, block_sizes)
    stream = _Stream(seed, f"trustlab-allocation-v1\x00{stratum}")
    index = 0
    block_number = 0
    while True:
        block = _block(stream, conditions, block_sizes)
        for position, condition in enumerate(block):
            yield SequenceEntry(index, block_number, len(block), position, condition)
            index += 1
        block_number += 1


def entry_at(
    seed: bytes, stratum: str, conditions: Sequence[str], block_sizes: Sequence[int], index: int
) -> SequenceEntry:
    """The ``index``-th entry of a stratum's sequence (linear in ``index``: a hash per block)."""
    if index < 0:
        raise ValueError("index must be non-negative")
    for entry in sequence(seed, stratum, conditions, block_sizes):
        if entry.index == index:
            return entry
    raise AssertionError("unreachable: the sequence is infinite")  # pragma: no cover


def pilot_seed(seed: bytes) -> bytes:
    """The seed of a study's pilot sequence: derived from the study's seed under its own key, so
    that the pilot's allocations (which staff see, and which a reset deletes) tell nothing of the
    live sequence, and the live sequence starts at its first entry when the study goes live."""
    return hmac.new(seed, b"trustlab-pilot-sequence-v1", hashlib.sha256).digest()


def sequence_seed(study_seed_hex: str, *, pilot: bool) -> bytes:
    """The seed of a study's live sequence (its stored seed), or of its pilot's."""
    seed = bytes.fromhex(study_seed_hex)
    return pilot_seed(seed) if pilot else seed


def stratum_key(values: dict[str, str]) -> str:
    """A canonical name for a stratum, e.g. ``gender=female;site=b`` ("" when unstratified)."""
    return ";".join(f"{key}={values[key]}" for key in sorted(values))
