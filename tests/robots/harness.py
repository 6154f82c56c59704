"""Running a bridge against the test's own app: the app served on loopback by uvicorn in a
thread (the lab fixture's TestClient keeps driving the experimenter's and tablet's side), and
the bridge on its own event loop in another thread, as the ``trustlab bridge`` process runs it."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from typing import Any

import uvicorn
from fastapi import FastAPI
from sqlalchemy import select

from app.robots.bridge import Bridge, BridgeSettings, Trigger
from app.robots.robot import Robot
from app.services.sessions import verify
from app.tables import Answer
from tests.conftest import Lab
from tests.servers import free_port

BOUND = 30.0
"""Seconds after which a wait in these tests fails instead of hanging (never reached when
the code works: every wait is on an event)."""


@contextlib.contextmanager
def served(app: FastAPI, port: int | None = None) -> Iterator[str]:
    """Serve ``app`` (already started by the test's TestClient) on ``port`` (default: a free
    one) on loopback; leaving the block stops serving, as a server going away would."""
    port = port or free_port()
    config = uvicorn.Config(
        app,
        host="127.0.0.1",
        port=port,
        lifespan="off",
        log_level="critical",
        timeout_graceful_shutdown=0,  # open WebSockets are cut, as when a server goes away
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="uvicorn", daemon=True)
    thread.start()
    try:
        for _ in range(int(BOUND / 0.01)):
            if server.started:
                break
            threading.Event().wait(0.01)
        assert server.started, "the test server did not start"
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(BOUND)


class RunningBridge:
    """A bridge in a thread: :attr:`started` resolves once it joined (or with its refusal),
    :attr:`lines` is what it printed; leaving the ``with`` block stops it (bounded)."""

    def __init__(self, robot: Robot, url: str, station: str, key: str, **settings: Any) -> None:
        self.settings = BridgeSettings(
            url=url,
            station=station,
            key=key,
            trigger=settings.pop("trigger", Trigger.CONSOLE),
            retry_delay=settings.pop("retry_delay", 0.05),
            max_retry_delay=settings.pop("max_retry_delay", 0.2),
            cue_poll_seconds=settings.pop("cue_poll_seconds", 0.05),
            **settings,
        )
        self.robot = robot
        self.lines: list[str] = []
        self.started: Future[None] = Future()
        self.finished: Future[None] = Future()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._bridge: Bridge | None = None
        self._thread = threading.Thread(target=self._main, name="bridge", daemon=True)

    def _main(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:
            if not self.started.done():
                self.started.set_exception(exc)
            self.finished.set_exception(exc)
        else:
            self.finished.set_result(None)

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._bridge = Bridge(self.robot, self.settings, say=self.lines.append)
        await self._bridge.start()
        self.started.set_result(None)
        try:
            await self._bridge.run()
        finally:
            await self._bridge.close()

    def __enter__(self) -> RunningBridge:
        self._thread.start()
        self.started.result(BOUND)
        return self

    def stop(self) -> None:
        """Stop the bridge as Ctrl-C does, and wait for it (bounded)."""
        if self._loop is not None and self._bridge is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._bridge.stop)
        self._thread.join(BOUND)
        assert not self._thread.is_alive(), "the bridge did not stop"

    def __exit__(self, *exc: object) -> None:
        self.stop()


def ask_now(lab: Lab, category: str = "conation") -> dict[str, Any]:
    """The operator console's "ask now" (a Wizard-of-Oz prompt): the step as staff see it."""
    response = lab.experimenter.post(
        f"/api/v1/stations/{lab.station}/prompts", json={"category": category}
    )
    assert response.status_code in (200, 201), response.text
    return dict(response.json())


def stored_answers(lab: Lab) -> list[Answer]:
    with lab.database.read_session() as db:
        return list(db.scalars(select(Answer).order_by(Answer.id)))


def console_badge(lab: Lab, label: str = "pepper") -> str:
    """What the station's console shows of the device key ``label``: "connected" or "not
    connected"."""
    console = lab.experimenter.get(f"/stations/{lab.station}").text
    if f'{label}: <span class="badge open">connected</span>' in console:
        return "connected"
    assert f'{label}: <span class="badge">not connected</span>' in console, console
    return "not connected"


def wait_for(condition: Callable[[], bool]) -> None:
    """Poll what the bridge's thread brings about (bounded by :data:`BOUND`, not timed)."""
    for _ in range(int(BOUND / 0.02)):
        if condition():
            return
        threading.Event().wait(0.02)
    raise AssertionError("the bridge never got there")


def assert_verify_clean(lab: Lab) -> None:
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.findings
