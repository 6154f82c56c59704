"""Simulated online participants: each comes through the study's public link, as a person sent by
a recruitment platform would, in a browser of its own (a cookie jar), with no experimenter.

A bot opens ``/join/STUDY?ID=…`` and passes the browser check, then does what ``/online`` asks,
page after page: it loads each questionnaire page and submits its form (with the page's timing,
as static/js/tablet.js does), and in the room it takes the device key from the page, presses
*start* and answers the robot over the room's WebSocket as the paper's rules say (app.bots), until
the completion page. A :class:`Pace` paces it like a person (pauses to read and answer a page, to
walk to the next zone, to answer the robot; none for tests), and ``arrivals_seconds`` spreads the
participants' arrivals as a platform's do. Every request's latency can be recorded by kind
(``join``: the link's page, ``online``: ``/online``, which sends them on or shows the room,
``page``: a questionnaire page, ``form``: a submission, ``start``, ``prompt``, ``answer``) for
the scale benchmark (bench/online.py).

The bots sign in as an admin only to read the protocol (the rules a participant is told, and the
answers an attentive participant gives to its attention checks); everything they do as
participants goes through the public routes.
"""

from __future__ import annotations

import asyncio
import random
import re
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, TypeVar
from urllib.parse import urlencode

import httpx

from app.bots import (
    BotConfig,
    BotSummary,
    _Category,
    _Robot,
    answer_session,
    attention_answers,
    categories_of,
    check_config,
    preferences,
    questionnaire_answers,
)
from app.client import ApiError, ExperimenterClient, StationSocket, http_client

Recorder = Callable[[str, float], None]
"""Called with each request's kind and its latency in seconds."""
T = TypeVar("T")

DESKTOP_CHECK = {"webgl": "1", "audio": "1", "width": "1440", "height": "900", "keyboard": "1"}
"""What a desktop browser's check reports (static/js/online_check.js)."""
FORM_TOKEN = re.compile(r'name="csrf_token" value="([^"]+)"')
ROOM_KEY = re.compile(r'data-key="([^"]+)"')
OUTCOME = re.compile(r'data-outcome="([a-z_]+)"')
MOST_PAGES = 200
"""A participant who has not finished after this many pages is stuck (a defect): stop them."""


class OnlineStudyClosed(Exception):
    """The study is not run online, or refused a bot: nothing to simulate."""


@dataclass(frozen=True)
class Pace:
    """How fast a simulated participant goes: the mean seconds of each kind of pause (each
    drawn from an exponential distribution). All zero, the default, is a machine's pace."""

    action: float = 0.0
    """Before each submission, session start and answer: reading, deciding, pressing."""
    per_item: float = 0.0
    """Added before a questionnaire page's submission for each item on it."""
    walk: float = 0.0
    """In the room, before each question: walking to the next zone."""

    def __post_init__(self) -> None:
        if min(self.action, self.per_item, self.walk) < 0:
            raise ValueError("a pace's pauses are seconds ≥ 0")


HUMAN_PACE = Pace(action=2.0, per_item=3.0, walk=5.0)
"""A person's pace: about 3 s per questionnaire item (above the 2 s per item under which
app.quality flags a page as sped through), 5 s to walk to a zone, 2 s to decide and press."""


class _Participant:
    """One simulated online participant in a browser of its own."""

    def __init__(
        self,
        config: BotConfig,
        recruitment_id: str,
        parameters: dict[str, str],
        rng: random.Random,
        categories: list[_Category],
        attention: dict[str, str],
        pace: Pace,
        record: Recorder,
        on_step: Callable[[], None],
        condition_of: Callable[[str], Awaitable[str]],
    ) -> None:
        self.config = config
        self.condition_of = condition_of
        self.query = urlencode(parameters)
        self.rng = rng
        self.preferred = preferences(categories, rng)
        self.attention = attention
        self.pace = pace
        self.record = record
        self.on_step = on_step
        self.browser = http_client(config.url, timeout=30.0)
        self.tablet: httpx.AsyncClient | None = None
        self.recruitment_id = recruitment_id
        self.condition = ""
        self.sessions = 0
        self.submitted = 0

    async def _timed(self, kind: str, call: Awaitable[T]) -> T:
        started = time.perf_counter()
        result = await call
        self.record(kind, time.perf_counter() - started)
        return result

    async def pause(self, mean: float) -> None:
        """A person's pause of ``mean`` seconds on average (none when it is 0)."""
        if mean > 0:
            await asyncio.sleep(self.rng.expovariate(1.0 / mean))

    async def think(self) -> None:
        """Before an action: deciding and pressing."""
        await self.pause(self.pace.action)

    async def walk(self) -> None:
        """In the room: to the next zone."""
        await self.pause(self.pace.walk)

    async def _page(self, path: str, kind: str = "page") -> httpx.Response:
        response = await self._timed(kind, self.browser.get(path))
        if response.status_code >= 400:
            raise ApiError(response.status_code, f"{path}: {_said(response.text)}")
        return response

    async def _submit(self, path: str, form: dict[str, Any]) -> httpx.Response:
        await self.think()
        response = await self._timed("form", self.browser.post(path, data=form))
        if response.status_code not in (200, 303):
            raise ApiError(response.status_code, f"{path}: {_said(response.text)}")
        return response

    async def join(self) -> None:
        """The public link, then the browser check's verdict; ApiError when not enrolled."""
        await self._page(f"/join/{self.config.study}?{self.query}", kind="join")
        browser = f"bot-browser-{secrets.token_hex(8)}"
        joined = await self._submit(
            f"/join/{self.config.study}", {"query": self.query, "browser": browser, **DESKTOP_CHECK}
        )
        if joined.status_code != 303:
            outcome = OUTCOME.search(joined.text)
            raise OnlineStudyClosed(
                f"{self.recruitment_id} was not enrolled: "
                f"{outcome.group(1) if outcome else _said(joined.text)}"
            )
        token = self.browser.cookies.get("tl_tablet")
        assert token, "the join set no tablet cookie"
        # The page's own items come from the tablet's JSON view of the same page (what the
        # participant reads); the answers go back through the page's form.
        self.tablet = http_client(
            self.config.url, timeout=30.0, headers={"Authorization": f"Bearer {token}"}
        )

    async def run(self) -> str:
        """From the link to the completion page; returns the outcome the last page names."""
        await self.join()
        for _ in range(MOST_PAGES):
            where = await self._timed("online", self.browser.get("/online"))
            if where.status_code == 303:
                await self._questionnaire(where.headers["location"])
                continue
            if where.status_code != 200:
                raise ApiError(where.status_code, f"/online: {_said(where.text)}")
            outcome = OUTCOME.search(where.text)
            if outcome:
                return outcome.group(1)
            key = ROOM_KEY.search(where.text)
            if key is None:
                raise ApiError(500, "/online showed neither a page, the room nor an outcome")
            await self._room(key.group(1))
        raise ApiError(500, f"{self.recruitment_id} never finished ({MOST_PAGES} pages)")

    async def _questionnaire(self, path: str) -> None:
        shown = await self._page(path)
        token = FORM_TOKEN.search(shown.text)
        if token is None:
            raise ApiError(500, f"{path} has no form")
        opened = time.monotonic()
        assert self.tablet is not None
        shown_json = await self.tablet.get("/api/v1/tablet")
        if shown_json.status_code != 200:  # a busy server's 503, say: this participant stops
            raise ApiError(shown_json.status_code, f"/api/v1/tablet: {shown_json.text[:120]}")
        page = shown_json.json()
        form: dict[str, Any] = {"csrf_token": token.group(1)}
        if page["kind"] == "language":
            form["language"] = self.rng.choice([offered["code"] for offered in page["languages"]])
            await self._submit("/tablet/language", form)
        elif page["kind"] == "consent":
            form |= {"accept": "yes", "version": str(page["consent"]["number"])}
            await self._submit("/tablet/consent", form)
        elif page["kind"] == "questionnaire":
            if not self.condition:  # the participant does not know it; their answers show it
                self.condition = await self.condition_of(page["participant"])
            answers = questionnaire_answers(
                page, self.config.responses, self.condition, self.rng, self.attention
            )
            form |= {key: str(value) for key, value in answers.items()}
            await self.pause(self.pace.action + self.pace.per_item * len(answers))
            form["page-seconds"] = f"{time.monotonic() - opened:.3f}"
            form["away-seconds"] = "0"
            await self._timed("form", self.browser.post(path, data=form))
        else:
            raise ApiError(500, f"{path}: the tablet shows {page['kind']!r}")
        self.submitted += 1

    async def _room(self, key: str) -> None:
        """Start the next session and answer it through the room's socket."""
        await self.think()
        started = await self._timed("start", self.browser.post("/online/start"))
        if started.status_code not in (204, 409):  # 409: a session already runs (a reload)
            raise ApiError(started.status_code, f"/online/start: {_said(started.text)}")
        socket = StationSocket(self.config.url, key)
        await socket.open()
        try:
            state = await socket.current_state()
            if state.expected.action == "prompt":
                await answer_session(
                    _TimedRobot(socket, self._timed),
                    state.expected.categories,
                    self.preferred,
                    rng=self.rng,
                    noise=self.config.noise,
                    on_step=self.on_step,
                    think=self.think,
                    walk=self.walk,
                )
                self.sessions += 1
        finally:
            await socket.close()

    async def aclose(self) -> None:
        await self.browser.aclose()
        if self.tablet is not None:
            await self.tablet.aclose()


class _TimedRobot(_Robot):
    """The room's socket, each prompt and answer timed."""

    def __init__(
        self, socket: StationSocket, timed: Callable[[str, Awaitable[Any]], Awaitable[Any]]
    ) -> None:
        super().__init__(None, socket)
        self._time = timed

    async def prompt(self, category: str) -> Any:
        return await self._time("prompt", super().prompt(category))

    async def answer(self, step_id: int, answer: Any) -> Any:
        return await self._time("answer", super().answer(step_id, answer))


def _said(page: str) -> str:
    """A refusal page's heading (or the start of a JSON body), for an error line."""
    heading = re.search(r"<h1[^>]*>(.*?)</h1>", page, re.S)
    return re.sub(r"\s+", " ", heading.group(1)).strip() if heading else page[:120]


def _parameters(
    online: dict[str, Any], protocol: dict[str, Any], recruitment_id: str, rng: random.Random
) -> dict[str, str]:
    """The link's parameters a platform would send: the ID, and each further parameter (a
    stratification factor's value drawn from those the protocol allows)."""
    allowed = protocol.get("allocation", {}).get("strata_values", {})
    values = {online["id_parameter"]: recruitment_id}
    for name in online.get("parameters", []):
        choices = allowed.get(name)
        values[name] = rng.choice(choices) if choices else f"bot-{name.lower()}"
    return values


async def run_online_bots(
    config: BotConfig,
    *,
    pace: Pace = Pace(),
    arrivals_seconds: float = 0.0,
    tick: Callable[[], None] = lambda: None,
    record: Recorder = lambda _kind, _seconds: None,
) -> BotSummary:
    """Drive ``config.participants`` simulated online participants through the study's public
    link, ``config.concurrency`` at once, arriving one after another evenly over
    ``arrivals_seconds`` (0: all at once). OnlineStudyClosed when the study is not run online."""
    check_config(config)
    if arrivals_seconds < 0:
        raise ValueError("arrivals_seconds must be ≥ 0")
    started = time.perf_counter()
    summary = BotSummary()
    rng = random.Random(config.seed)
    async with ExperimenterClient(config.url) as admin:
        await admin.sign_in(config.username, config.password)
        protocol = await admin.protocol(config.study)
        if not protocol.get("online"):
            raise OnlineStudyClosed(
                f"study {config.study!r} is not run online: its protocol has no [online]"
            )

        async def condition_of(code: str) -> str:
            found = await admin.call("GET", f"/studies/{config.study}/participants/{code}")
            return str(found.get("condition") or "")

        arrivals = _Arrivals(arrivals_seconds, config.participants)
        await _run(config, protocol, pace, arrivals, tick, record, condition_of, summary, rng)
    summary.seconds = round(time.perf_counter() - started, 3)
    return summary


class _Arrivals:
    """When each participant arrives, evenly over a window, and how many were in at once."""

    def __init__(self, seconds: float, participants: int) -> None:
        self.every = seconds / max(participants, 1)
        self.began = time.monotonic()
        self.active = 0

    async def wait_for(self, index: int) -> None:
        """Until participant ``index`` (from 0) arrives."""
        await asyncio.sleep(max(0.0, self.began + index * self.every - time.monotonic()))

    def arrived(self, summary: BotSummary) -> None:
        self.active += 1
        summary.most_at_once = max(summary.most_at_once, self.active)

    def left(self) -> None:
        self.active -= 1


async def _run(
    config: BotConfig,
    protocol: dict[str, Any],
    pace: Pace,
    arrivals: _Arrivals,
    tick: Callable[[], None],
    record: Recorder,
    condition_of: Callable[[str], Awaitable[str]],
    summary: BotSummary,
    rng: random.Random,
) -> None:
    online: dict[str, Any] = protocol["online"]
    categories = categories_of(protocol)
    attention = attention_answers(protocol)
    run = secrets.token_hex(4)  # a second run's IDs are new participants, not returns
    queue: asyncio.Queue[int] = asyncio.Queue()
    for index in range(config.participants):
        queue.put_nowait(index)

    def answered() -> None:
        summary.steps += 1
        tick()

    async def worker(worker_rng: random.Random) -> None:
        while not queue.empty():
            index = queue.get_nowait()
            await arrivals.wait_for(index)
            recruitment_id = f"{config.station_prefix}-{run}-{index + 1}"
            person_rng = random.Random(worker_rng.random())
            participant = _Participant(
                config,
                recruitment_id,
                _parameters(online, protocol, recruitment_id, person_rng),
                person_rng,
                categories,
                attention,
                pace,
                record,
                answered,
                condition_of,
            )
            summary.participants += 1
            arrivals.arrived(summary)
            try:
                outcome = await participant.run()
                if outcome == "completed":
                    summary.completed += 1
                else:
                    summary.errors.append(f"{recruitment_id}: ended as {outcome}")
            except (ApiError, OnlineStudyClosed, httpx.HTTPError, OSError) as exc:
                summary.errors.append(f"{recruitment_id}: {type(exc).__name__}: {exc}")
            finally:
                arrivals.left()
                summary.sessions += participant.sessions
                summary.questionnaires += participant.submitted
                await participant.aclose()

    workers = [
        asyncio.ensure_future(worker(random.Random(rng.random())))
        for _ in range(min(config.concurrency, max(config.participants, 1)))
    ]
    try:
        await asyncio.gather(*workers)
    finally:
        for task in workers:
            task.cancel()
        await asyncio.gather(*workers, return_exceptions=True)
