"""Make the recogniser tests' WAV files (run once; the files are committed).

    apt-get install -y espeak-ng
    .venv/bin/python tests/speech/data/make_wavs.py

Each phrase is said by espeak-ng's US-English voice, trimmed, put between 0.1 s of quiet room
noise (a fixed seed, about -60 dBFS, as a real microphone has) and written as 16 kHz mono
16-bit (15-25 KB each; the tests append the silence endpointing needs). ``cough.wav`` is two
band-limited noise bursts, ``silence.wav`` room noise only, and ``yes_stereo_44k_float.wav`` a
quick "yes" with no padding as 44.1 kHz stereo 32-bit float, for the conversion (kept short:
that format takes 350 KB a second). Re-running rewrites the files; they only come out the same
with the same espeak-ng.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.signal import resample_poly

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))

from app.speech.wav import read_wav, to_pcm16  # noqa: E402

PHRASES = {
    "yes": "yes",
    "no": "no",
    "yeah": "yeah",
    "nope": "nope",
    "no_way": "no way",
    "sure": "sure",
    "maybe": "maybe",
    "i_dont_know": "I don't know",
}
RATE = 16000
QUIET = 0.1
SPEED = 190


def speak(text: str, folder: Path, speed: int = SPEED) -> np.ndarray:
    out = folder / "say.wav"
    subprocess.run(
        ["espeak-ng", "-v", "en-us", "-s", str(speed), "-w", str(out), text], check=True, timeout=60
    )
    samples = np.frombuffer(read_wav(out), "<i2").astype(np.float64) / 32768.0
    loud = np.flatnonzero(np.abs(samples) > 1e-3)
    return samples[loud[0] : loud[-1] + 1]


def padded(sound: np.ndarray, rng: np.random.Generator, quiet_seconds: float = QUIET) -> np.ndarray:
    quiet = np.zeros(int(quiet_seconds * RATE))
    signal = np.concatenate([quiet, sound, quiet])
    return signal + rng.normal(0.0, 0.001, signal.size)


def write_pcm16(path: Path, signal: np.ndarray) -> None:
    data = to_pcm16(signal)
    fmt = struct.pack("<HHIIHH", 1, 1, RATE, RATE * 2, 2, 16)
    path.write_bytes(_riff(fmt, data))


def write_float_stereo_44k(path: Path, signal: np.ndarray) -> None:
    rate = 44100
    upsampled = resample_poly(signal, 441, 160)
    stereo = np.stack([upsampled, 0.8 * upsampled], axis=1).astype("<f4")
    fmt = struct.pack("<HHIIHH", 3, 2, rate, rate * 8, 8, 32)
    path.write_bytes(_riff(fmt, stereo.tobytes()))


def _riff(fmt: bytes, data: bytes) -> bytes:
    body = b"WAVE" + b"fmt " + struct.pack("<I", len(fmt)) + fmt
    body += b"data" + struct.pack("<I", len(data)) + data
    return b"RIFF" + struct.pack("<I", len(body)) + body


def cough(rng: np.random.Generator) -> np.ndarray:
    parts = []
    for decay in (0.07, 0.05):
        n = int(0.22 * RATE)
        spectrum = np.fft.rfft(rng.normal(size=n))
        frequencies = np.fft.rfftfreq(n, 1 / RATE)
        spectrum[(frequencies < 300) | (frequencies > 3500)] = 0
        t = np.arange(n) / RATE
        burst = np.fft.irfft(spectrum, n) * np.minimum(1.0, t / 0.01) * np.exp(-t / decay)
        parts += [0.3 * burst / np.abs(burst).max(), np.zeros(int(0.1 * RATE))]
    return np.concatenate(parts[:-1])


def main() -> None:
    rng = np.random.default_rng(38)
    with tempfile.TemporaryDirectory() as folder:
        for name, text in PHRASES.items():
            sound = speak(text, Path(folder))
            write_pcm16(HERE / f"{name}.wav", padded(sound, rng))
            if name == "yes":
                quick = speak(text, Path(folder), speed=240)
                write_float_stereo_44k(HERE / "yes_stereo_44k_float.wav", padded(quick, rng, 0.0))
    write_pcm16(HERE / "cough.wav", padded(cough(rng), rng))
    write_pcm16(HERE / "silence.wav", padded(np.zeros(int(0.2 * RATE)), rng))


if __name__ == "__main__":
    main()
