"""``trustlab speech recognize``: the offline recogniser on a WAV file.

A lab records a "yes" in its room with its microphone and checks what the server would hear, how
sure it is and how long it takes, before any participant comes in.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer

from app.cli.common import JsonFlag, emit_json
from app.cli.errors import fail

speech_cli = typer.Typer(help="Offline speech recognition (yes/no answers).", no_args_is_help=True)


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.add_typer(speech_cli, name="speech")


@speech_cli.command("recognize")
def recognize(
    file: Annotated[Path, typer.Argument(help="A WAV file (any rate, channels, PCM or float).")],
    protocol: Annotated[
        Path | None,
        typer.Option(
            "--protocol",
            help="Use this protocol file's \\[speech] phrases, min_confidence, engine and "
            "prompt_phrases (default: the default phrases).",
        ),
    ] = None,
    engine: Annotated[
        str | None,
        typer.Option(
            "--engine",
            help="The recogniser: whisper or pocketsphinx (default: the protocol's, else whisper).",
        ),
    ] = None,
    prompt_phrases: Annotated[
        bool | None,
        typer.Option(
            "--prompt-phrases/--no-prompt-phrases",
            help="Whisper: prime the decode with the phrases, or not (default: the protocol's, "
            "else on).",
        ),
    ] = None,
    as_json: JsonFlag = False,
) -> None:
    """Recognise a yes or a no in FILE: answer, transcript, confidence and time taken."""
    from app.protocol import SpeechSpec, load_protocol_file
    from app.speech.engines import ENGINES, EngineSettings, make_recognizer
    from app.speech.vocabulary import Vocabulary
    from app.speech.wav import read_wav

    spec = SpeechSpec() if protocol is None else load_protocol_file(protocol).protocol.speech
    if engine is not None and engine not in ENGINES:
        fail(f"unknown engine {engine!r}: one of {', '.join(ENGINES)}", 2)
    chosen_here = {"engine": engine, "prompt_phrases": prompt_phrases}
    spec = spec.model_copy(update={k: v for k, v in chosen_here.items() if v is not None})
    vocabulary = Vocabulary.of(spec.yes, spec.no, spec.min_confidence)
    chosen = EngineSettings.of(spec)
    try:
        pcm = read_wav(file)
    except ValueError as exc:
        fail(f"{file}: {exc}", 2)
    loading = time.perf_counter()
    recognizer: Any = make_recognizer(vocabulary, chosen)
    load_seconds = time.perf_counter() - loading
    started = time.perf_counter()
    result = recognizer.recognize(pcm)
    total = time.perf_counter() - started
    answer = result.answer or "unclear"
    if as_json:
        emit_json(
            {
                "file": str(file),
                "answer": answer,
                "transcript": result.transcript,
                "heard": result.heard,
                "confidence": round(result.confidence, 4),
                "engine": result.engine,
                "prompt_phrases": chosen.prompt,
                "load_seconds": round(load_seconds, 4),
                "seconds": round(result.seconds, 4),
                "total_seconds": round(total, 4),
                "audio_seconds": round(len(pcm) / 32000, 3),
            }
        )
        return
    typer.echo(f"answer:     {answer}")
    typer.echo(f"transcript: {result.transcript or '(silence)'}")
    typer.echo(f"heard:      {result.heard or '(nothing)'} (unconstrained, for comparison)")
    typer.echo(f"confidence: {result.confidence:.2f} (needs {vocabulary.min_confidence:g})")
    typer.echo(f"engine:     {result.engine} (loaded in {load_seconds:.2f} s)")
    typer.echo(
        f"time:       {total * 1000:.0f} ms for {len(pcm) / 32000:.2f} s of audio, "
        f"final decode {result.seconds * 1000:.0f} ms"
    )
