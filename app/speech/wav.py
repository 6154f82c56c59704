"""Reading a WAV file into what the recogniser takes: 16 kHz mono signed 16-bit little-endian.

Labs record with whatever they have (a phone at 44.1 kHz stereo, an interface writing 24-bit or
float), so any PCM or IEEE-float WAV is converted: channels are averaged, the rate is resampled
(polyphase, so no aliasing from a plain decimation), samples are scaled to int16. Anything else
(an MP3 renamed .wav, a truncated file, a header with no channels) is refused with one line, as a
:class:`ValueError`, because a silent misreading would look like a recogniser that cannot hear.

Python's :mod:`wave` is not used: before 3.12 it reads neither float nor WAVE_FORMAT_EXTENSIBLE.
"""

from __future__ import annotations

import struct
from math import gcd
from pathlib import Path

import numpy as np
from scipy.signal import resample_poly

TARGET_RATE = 16000

_PCM, _FLOAT, _EXTENSIBLE = 0x0001, 0x0003, 0xFFFE
_STREAMING_SIZES = (0, 0xFFFFFFFF)
"""Data sizes a recorder writes when it never went back to fill in the real one."""


def read_wav(path: Path) -> bytes:
    """The file's audio as 16 kHz mono int16 LE; ValueError (one line) for anything not a WAV."""
    try:
        blob = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from exc
    return decode_wav(blob)


def decode_wav(blob: bytes) -> bytes:
    """:func:`read_wav` for bytes already in memory."""
    channels, rate, samples = _parse(blob)
    mono = samples.reshape(-1, channels).mean(axis=1) if channels > 1 else samples
    return to_pcm16(resample(mono, rate))


def resample(signal: np.ndarray, rate: int, target: int = TARGET_RATE) -> np.ndarray:
    """``signal`` (floats in -1..1) at ``rate`` resampled to ``target`` Hz."""
    if rate == target or signal.size == 0:
        return signal
    common = gcd(rate, target)
    return np.asarray(resample_poly(signal, target // common, rate // common))


def to_pcm16(signal: np.ndarray) -> bytes:
    """Floats in -1..1 as int16 LE bytes (clipped, rounded)."""
    scaled = np.clip(np.rint(signal * 32768.0), -32768, 32767)
    return scaled.astype("<i2").tobytes()


def _parse(blob: bytes) -> tuple[int, int, np.ndarray]:
    """(channels, rate, interleaved samples as floats in -1..1) of a RIFF/WAVE file."""
    if len(blob) < 12 or blob[:4] != b"RIFF" or blob[8:12] != b"WAVE":
        raise ValueError("not a WAV file (no RIFF/WAVE header)")
    fmt: bytes | None = None
    position = 12
    while position + 8 <= len(blob):
        chunk_id = blob[position : position + 4]
        size = struct.unpack_from("<I", blob, position + 4)[0]
        body_start = position + 8
        if chunk_id == b"fmt ":
            fmt = blob[body_start : body_start + size]
        elif chunk_id == b"data":
            if fmt is None:
                raise ValueError("malformed WAV: the data chunk comes before the fmt chunk")
            available = len(blob) - body_start
            if size in _STREAMING_SIZES:
                size = available
            elif size > available:
                declared = f"{size} bytes of audio declared, {available} present"
                raise ValueError(f"truncated WAV: {declared}")
            return _samples(fmt, blob[body_start : body_start + size])
        position = body_start + size + (size & 1)
    if fmt is None:
        raise ValueError("malformed WAV: no fmt chunk")
    raise ValueError("malformed WAV: no data chunk")


def _samples(fmt: bytes, data: bytes) -> tuple[int, int, np.ndarray]:
    if len(fmt) < 16:
        raise ValueError("malformed WAV: fmt chunk too short")
    tag, channels, rate, _, block_align, bits = struct.unpack_from("<HHIIHH", fmt)
    if tag == _EXTENSIBLE:
        if len(fmt) < 26:
            raise ValueError("malformed WAV: extensible fmt chunk too short")
        tag = struct.unpack_from("<H", fmt, 24)[0]
    if channels == 0:
        raise ValueError("malformed WAV: 0 channels")
    if rate == 0:
        raise ValueError("malformed WAV: sample rate 0")
    width = bits // 8
    if bits % 8 or block_align != width * channels:
        raise ValueError(f"unsupported WAV layout: {bits}-bit samples in {block_align}-byte frames")
    usable = len(data) - len(data) % block_align
    raw = data[:usable]
    if tag == _PCM and bits == 8:
        samples = (np.frombuffer(raw, np.uint8).astype(np.float64) - 128.0) / 128.0
    elif tag == _PCM and bits == 16:
        samples = np.frombuffer(raw, "<i2").astype(np.float64) / 32768.0
    elif tag == _PCM and bits == 24:
        triples = np.frombuffer(raw, np.uint8).reshape(-1, 3).astype(np.int32)
        joined = triples[:, 0] | (triples[:, 1] << 8) | (triples[:, 2] << 16)
        samples = np.where(joined >= 1 << 23, joined - (1 << 24), joined) / float(1 << 23)
    elif tag == _PCM and bits == 32:
        samples = np.frombuffer(raw, "<i4").astype(np.float64) / float(1 << 31)
    elif tag == _FLOAT and bits in (32, 64):
        samples = np.frombuffer(raw, "<f4" if bits == 32 else "<f8").astype(np.float64)
        samples = np.nan_to_num(np.clip(samples, -1.0, 1.0))
    else:
        kind = {_PCM: "PCM", _FLOAT: "float"}.get(tag, f"format 0x{tag:04x}")
        raise ValueError(f"unsupported WAV encoding: {kind} with {bits}-bit samples")
    return channels, rate, samples
