"""``trustlab robot`` (a console robot) and ``trustlab bots`` (simulated participants)."""

from __future__ import annotations

import json
import sys
import uuid
from typing import TYPE_CHECKING, Annotated, Any, Literal

import typer

from app.cli.common import JsonFlag, emit_json
from app.cli.errors import fail
from app.errors import InvalidInput

if TYPE_CHECKING:
    from app.client import ApiError, StationSocket


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.command("robot")(robot)
    cli.command("bots")(bots)


def _show_state(state: dict[str, Any]) -> None:
    from app.services.sessions.runtime import session_label

    who = state.get("participant") or "nobody"
    session = state.get("session")
    run = state.get("run")
    where = ""
    if session:
        where = f", {session_label(session['number'])} ({session['status']})"
        if run:
            where += f", run {run['number']} ({run['status']})"
    typer.echo(f"[{state['station']}] {who}{where}")
    typer.echo(f"  next: {state['expected']['message']}")


BUSY = 503
"""The status of a server that cannot serve right now (e.g. its database restarts): retry."""


class _ConnectionLost(Exception):
    """The station WebSocket is gone and the client's own reconnection gave up."""


def _refusal(exc: ApiError, retry: str) -> None:
    """One line for a refused request: busy (503, ``retry`` says how) or refused (4xx)."""
    if exc.status == BUSY:
        typer.echo(f"  server unavailable: {exc.detail}; {retry}")
    else:
        typer.echo(f"  refused: {exc.detail}")


async def _console(url: str, key: str) -> None:
    from websockets.exceptions import ConnectionClosed

    from app.client import DeviceKeyRefused, StationSocket

    async with StationSocket(url, key) as socket:
        assert socket.state is not None
        _show_state(socket.state)
        try:
            await _loop(socket)
        except DeviceKeyRefused:
            raise
        except (ConnectionError, ConnectionClosed, TimeoutError) as exc:
            raise _ConnectionLost(str(exc) or type(exc).__name__) from exc


async def _loop(socket: StationSocket) -> None:
    """Do what the server expects next until the user quits: answer the open prompt, prompt a
    category, or wait for an event; a refused request is shown and the state re-read.

    Only a state the robot asked for decides what comes next. A pushed event's state is a
    snapshot from when the event happened, and the events queue up while the robot prompts and
    asks: taking the oldest of them as the truth after the session's last answer asked that
    session's first question again. So an event only means "something changed": the robot then
    asks for the state (:func:`_fresh_state`).
    """
    from app.client import ApiError, DeviceKeyRefused

    state: dict[str, Any] = socket.state or {}
    while True:
        expected = state.get("expected") or {}
        action = expected.get("action")
        open_step = _open_step(state)
        if action == "answer" and open_step is not None:
            state = await _ask(socket, state, open_step["step_id"], open_step["question"])
        elif action == "prompt" and expected.get("categories"):
            chosen = await _choose(expected["categories"])
            if chosen is None:
                return
            try:
                step = await socket.prompt(chosen)
            except DeviceKeyRefused:
                raise
            except ApiError as exc:
                _refusal(exc, "choose the category again to retry")
                state = await _fresh_state(socket, state)
                continue
            state = await _ask(socket, state, step.step_id, step.question)
        else:
            typer.echo("  waiting for the experimenter… (Ctrl-C quits)")
            event = await socket.next_event()
            typer.echo(f"  event: {event.get('event', event['type'])}")
            # If the state cannot be read now, the event's snapshot is the newest news there is.
            state = await _fresh_state(socket, event.get("state") or state)


def _open_step(state: dict[str, Any]) -> dict[str, Any] | None:
    """The open prompt the server expects an answer to (its ``expected.step_id``), if any."""
    prompts: list[dict[str, Any]] = state.get("open_prompts") or []
    wanted = (state.get("expected") or {}).get("step_id")
    return next((p for p in prompts if p.get("step_id") == wanted), prompts[0] if prompts else None)


async def _choose(categories: list[str]) -> str | None:
    """The category the user picks from the expected ones (by number or name); None to quit."""
    import asyncio

    menu = "  ".join(f"{i}) {name}" for i, name in enumerate(categories, start=1))
    choice = (await asyncio.to_thread(input, f"category? {menu}  [q quits] ")).strip()
    if choice.lower() in {"q", "quit"}:
        return None
    if choice.isdigit() and 0 < int(choice) <= len(categories):
        return categories[int(choice) - 1]
    return choice


async def _ask(
    socket: StationSocket, state: dict[str, Any], step_id: int, question: str
) -> dict[str, Any]:
    """Ask ``question``, send the typed answer; return the station's state afterwards.

    A busy server (503) asks for the answer again and resends it with the same idempotency key,
    so an answer the server did record after all is not recorded twice. Any other refusal is
    shown and the state re-read.
    """
    import asyncio

    from app.client import ApiError, DeviceKeyRefused

    typer.echo(f"  robot: {question}")
    idempotency_key = uuid.uuid4().hex
    answered = _without_step(state, step_id)
    while True:
        said = (await asyncio.to_thread(input, "  participant (y/n)? ")).strip().lower()
        if said not in {"y", "yes", "n", "no"}:
            continue
        answer: Literal["yes", "no"] = "yes" if said.startswith("y") else "no"
        try:
            reply = await socket.answer(step_id, answer, idempotency_key=idempotency_key)
        except DeviceKeyRefused:
            raise
        except ApiError as exc:
            if exc.status == BUSY:
                _refusal(exc, "type the answer again to retry")
                continue
            _refusal(exc, "")
            return await _fresh_state(socket, answered)
        break
    typer.echo(
        f"  robot: {reply.reply}  (confidence {reply.confidence}, p = {reply.probability:.2f})"
    )
    typer.echo(f"  next: {reply.expected.message}")
    # the answer is recorded: should the state be unreadable, the reply says what comes next
    answered["expected"] = reply.expected.model_dump(mode="json")
    return await _fresh_state(socket, answered)


def _without_step(state: dict[str, Any], step_id: int) -> dict[str, Any]:
    """``state`` without the open prompt ``step_id`` (answered, or refused for good)."""
    prompts = state.get("open_prompts") or []
    return {**state, "open_prompts": [p for p in prompts if p.get("step_id") != step_id]}


async def _fresh_state(socket: StationSocket, fallback: dict[str, Any]) -> dict[str, Any]:
    """The station's state, read now; ``fallback`` (with the refusal shown) when refused.

    The events received until now are dropped unread: the state read after them includes what
    they report. Events arriving from now on stay queued, and each one read makes the robot ask
    again, so a change made while this request travels is not missed.
    """
    from app.client import ApiError, DeviceKeyRefused

    while not socket.events.empty():
        socket.events.get_nowait()
    try:
        return (await socket.current_state()).model_dump(mode="json")
    except DeviceKeyRefused:
        raise
    except ApiError as exc:
        _refusal(exc, "carrying on with the last known state")
        return fallback


def robot(
    url: Annotated[str, typer.Option(help="trustlab server, e.g. http://127.0.0.1:8000")],
    station: Annotated[str, typer.Option(help="The station this robot stands at.")],
    key: Annotated[str, typer.Option(help="The station's device key (tlk_…).")],
) -> None:
    """An interactive console robot: pick a category, read the question, type y/n."""
    import asyncio

    from websockets.exceptions import WebSocketException

    from app.client import ApiError, DeviceKeyRefused

    del station  # the key identifies the station; the option documents which one is meant
    try:
        asyncio.run(_console(url, key))
    except (KeyboardInterrupt, EOFError):
        typer.echo("")
    except DeviceKeyRefused as exc:
        raise InvalidInput(
            f"the server refused the device key: {exc.reason}; ask the experimenter for a new key"
        ) from exc
    except _ConnectionLost as exc:
        fail(f"lost the connection to {url}: {exc}; start the robot again once the server is back")
    except ApiError as exc:
        fail(f"the server refused: {exc.detail}")
    except (OSError, WebSocketException) as exc:
        raise InvalidInput(f"cannot reach {url}: {exc}") from exc


def bots(
    url: Annotated[str, typer.Option(help="trustlab server, e.g. http://127.0.0.1:8000")],
    study: Annotated[str, typer.Option(help="Study to enrol the simulated participants in.")],
    participants: Annotated[int, typer.Option(min=0, help="How many participants.")],
    concurrency: Annotated[int, typer.Option(min=1, help="Participants at once.")] = 4,
    username: Annotated[str, typer.Option(help="An admin account.")] = "admin",
    password_stdin: Annotated[
        bool, typer.Option("--password-stdin", help="Read the password from standard input.")
    ] = False,
    noise: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="Chance of answering against the rules.")
    ] = 0.0,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    transport: Annotated[str, typer.Option(help="ws or rest for the robot side.")] = "ws",
    language: Annotated[
        str | None,
        typer.Option(
            help="Enrol every participant in this language (default: the study's first, or a "
            "language drawn from those the tablet offers)."
        ),
    ] = None,
    station_prefix: Annotated[
        str,
        typer.Option(
            help="Name the bot stations PREFIX-1 … PREFIX-C (a second run beside a running one "
            "needs its own)."
        ),
    ] = "bot",
    online: Annotated[
        bool,
        typer.Option(
            "--online",
            help="Come through the study's public link as online participants would (an "
            "online study: docs/online.md); the station prefix starts their recruitment IDs.",
        ),
    ] = False,
    think_seconds: Annotated[
        float,
        typer.Option(
            min=0.0,
            help="With --online: a participant's mean pause before each submission and answer.",
        ),
    ] = 0.0,
    seconds_per_item: Annotated[
        float,
        typer.Option(
            min=0.0, help="With --online: more pause on a questionnaire page, per item on it."
        ),
    ] = 0.0,
    walk_seconds: Annotated[
        float,
        typer.Option(min=0.0, help="With --online: a mean walk to the next zone in the room."),
    ] = 0.0,
    arrivals_seconds: Annotated[
        float,
        typer.Option(
            min=0.0, help="With --online: participants arrive evenly over this many seconds."
        ),
    ] = 0.0,
    as_json: JsonFlag = False,
) -> None:
    """Simulated participants driven through the whole protocol over HTTP/WebSocket."""
    import asyncio

    from tqdm import tqdm

    from app.bots import BotConfig, BotStationsBusy, run_bots
    from app.bots_online import OnlineStudyClosed, Pace, run_online_bots
    from app.client import ApiError

    if not password_stdin:
        raise InvalidInput("give the admin password on standard input with --password-stdin")
    if transport not in ("ws", "rest"):
        raise InvalidInput("--transport is ws or rest")
    config = BotConfig(
        url=url,
        study=study,
        participants=participants,
        username=username,
        password=sys.stdin.readline().rstrip("\r\n"),
        concurrency=concurrency,
        noise=noise,
        seed=seed,
        transport=transport,  # type: ignore[arg-type]
        station_prefix=station_prefix,
        language=language,
    )
    with tqdm(desc="answers", unit="step", file=sys.stderr, disable=as_json) as bar:
        try:
            if online:
                pace = Pace(action=think_seconds, per_item=seconds_per_item, walk=walk_seconds)
                run = run_online_bots(
                    config, pace=pace, arrivals_seconds=arrivals_seconds, tick=bar.update
                )
            else:
                run = run_bots(config, tick=lambda: bar.update(1))
            summary = asyncio.run(run)
        except (BotStationsBusy, OnlineStudyClosed) as exc:
            raise InvalidInput(str(exc)) from exc
        except ApiError as exc:
            raise InvalidInput(f"the server refused: {exc.detail}") from exc
        except OSError as exc:
            raise InvalidInput(f"cannot reach {url}: {exc}") from exc
    if as_json:
        emit_json(summary.to_json())
    else:
        typer.echo(json.dumps(summary.to_json(), indent=2))
    if summary.errors:
        raise typer.Exit(1)
