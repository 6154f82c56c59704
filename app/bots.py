"""Simulated participants, driven through the whole protocol over real HTTP and WebSockets.

Each bot is enrolled and randomised like a person, given a tablet link, seated at one of the bot
stations, and taken through the study:

- its tablet gives consent and fills every questionnaire the flow asks for, answering with a
  :class:`ResponseModel`;
- an experimenter client starts each session when the server says one can start;
- a robot client (the station WebSocket by default, REST optionally) prompts the categories in a
  fresh random order every run, and the bot answers as the paper's rules say — "yes" to the
  category's preferred question, "no" to the others — each answer flipped with probability
  ``noise``.

Used for the demo study of ``make run``, for load tests and the crash test. A failure of one
participant is counted in the summary and the others carry on. The device keys a run issues for
its stations are revoked when it ends, also after an error or Ctrl-C, so no live key is left behind.
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, TypeVar

import httpx

from app.api.runtime_schemas import AnswerOut, IssuedDeviceOut, PromptOut
from app.client import ApiError, ExperimenterClient, RobotClient, StationSocket, http_client


@dataclass(frozen=True)
class ResponseModel:
    """Likert answers from a rounded normal, with a condition effect on per-session items.

    A participant of condition ``c`` answers per-session items around
    ``mean + effect[c] + slope[c] · (session − 1)`` and every other Likert item around ``mean``
    (in points of a 1-5 scale, rescaled to the item's scale); reverse-keyed items are mirrored;
    values are clipped to the scale.
    """

    mean: float = 3.0
    """Centre of the answers on a 1-5 scale."""
    sd: float = 0.9
    """Spread of the answers on a 1-5 scale."""
    effect: dict[str, float] = field(default_factory=lambda: {"C2": 0.7})
    """Shift of per-session answers, by condition id."""
    slope: dict[str, float] = field(default_factory=lambda: {"C2": 0.2})
    """Change per session of per-session answers, by condition id."""

    def likert(
        self, rng: random.Random, low: int, high: int, *, reverse: bool, shift: float
    ) -> int:
        """One answer on a ``low``..``high`` scale."""
        span = high - low
        centre = low + (self.mean - 1.0 + shift) / 4.0 * span
        value = min(high, max(low, round(rng.gauss(centre, self.sd * span / 4.0))))
        return low + high - value if reverse else value


@dataclass(frozen=True)
class BotConfig:
    """How many simulated participants, against which server, answering how."""

    url: str
    """Base URL of the trustlab server, e.g. http://127.0.0.1:8000."""
    study: str
    """Study to enrol the bots in."""
    participants: int
    """How many participants to simulate."""
    username: str
    """An admin account (bots create their stations and device keys)."""
    password: str
    """Its password."""
    concurrency: int = 4
    """Participants in progress at once (one bot station each)."""
    noise: float = 0.0
    """Probability of answering the robot against the rules."""
    seed: int = 0
    """Seeds preferences (where the protocol leaves them open), orders, noise and answers."""
    transport: Literal["ws", "rest"] = "ws"
    """How the robot side talks to the server."""
    station_prefix: str = "bot"
    """Bot stations are named PREFIX-1 … PREFIX-C."""
    responses: ResponseModel = field(default_factory=ResponseModel)
    """How the simulated participants answer the questionnaires."""
    language: str | None = None
    """Enrol every bot in this language; None: the study's default, or, where the tablet asks,
    a language drawn from those it offers."""


@dataclass
class BotSummary:
    """What the bots did."""

    participants: int = 0
    completed: int = 0
    sessions: int = 0
    steps: int = 0
    questionnaires: int = 0
    errors: list[str] = field(default_factory=list)
    seconds: float = 0.0
    most_at_once: int = 0
    """The most participants in the study at one moment (the online bots count it)."""

    def to_json(self) -> dict[str, Any]:
        """The summary as one JSON object."""
        return asdict(self)


@dataclass(frozen=True)
class _Category:
    name: str
    arms: int
    preferred: int | None


class _Robot:
    """Prompt and answer through whichever transport the config chose."""

    def __init__(self, rest: RobotClient | None, socket: StationSocket | None) -> None:
        self.rest = rest
        self.socket = socket

    async def prompt(self, category: str) -> PromptOut:
        if self.socket is not None:
            return await self.socket.prompt(category)
        assert self.rest is not None
        return await self.rest.prompt(category)

    async def answer(self, step_id: int, answer: Literal["yes", "no"]) -> AnswerOut:
        if self.socket is not None:
            return await self.socket.answer(step_id, answer)
        assert self.rest is not None
        return await self.rest.answer(step_id, answer)

    async def close(self) -> None:
        if self.socket is not None:
            await self.socket.close()
        if self.rest is not None:
            await self.rest.aclose()


def preferences(categories: list[_Category], rng: random.Random) -> dict[str, int]:
    """One participant's preferred question per category: the rules', or drawn where the
    protocol leaves it open (once per participant, so they answer alike in every session)."""
    return {
        c.name: c.preferred if c.preferred is not None else rng.randrange(c.arms)
        for c in categories
    }


def categories_of(protocol: dict[str, Any]) -> list[_Category]:
    """The protocol's categories: how many questions each has, and the rules' preferred one."""
    return [
        _Category(c["name"], len(c["questions"]), c.get("preferred"))
        for c in protocol["categories"]
    ]


def attention_answers(protocol: dict[str, Any]) -> dict[str, str]:
    """The expected answer of every attention-check item of a protocol (as the staff API shows
    it): the bots read what an attentive participant reads on the page."""
    return {
        item["key"]: str(item["expected"])
        for instrument in protocol["questionnaires"]["instruments"]
        for item in instrument["items"]
        if item.get("expected") is not None
    }


def questionnaire_answers(
    page: dict[str, Any],
    model: ResponseModel,
    condition: str,
    rng: random.Random,
    attention: dict[str, str] | None = None,
) -> dict[str, Any]:
    """Valid answers to the questionnaire on a tablet ``page`` (as ``GET /api/v1/tablet`` shows it),
    drawn from ``model``; session questionnaires shift by the condition's effect and slope, and
    attention checks get their ``attention`` answer (:func:`attention_answers`)."""
    scales = {s["name"]: s for s in page["scales"]}
    session = page.get("session")
    shift = 0.0
    if session is not None:
        shift = model.effect.get(condition, 0.0) + model.slope.get(condition, 0.0) * (session - 1)
    answers: dict[str, Any] = {}
    for item in page["instrument"]["items"]:
        if attention and item["key"] in attention:
            answers[item["key"]] = attention[item["key"]]
        elif item["kind"] == "likert":
            scale = scales[item["scale"]]
            answers[item["key"]] = model.likert(
                rng, scale["minimum"], scale["maximum"], reverse=item["reverse"], shift=shift
            )
        elif item["kind"] == "number":
            answers[item["key"]] = rng.randint(
                item["minimum"], max(item["minimum"], min(item["maximum"], 60))
            )
        elif item["kind"] == "choice":
            options = [o["value"] for o in item["options"] if not o["describe"]]
            answers[item["key"]] = rng.choice(options)
    return answers


class _Tablet:
    """A participant's tablet over the JSON tablet API."""

    def __init__(
        self,
        url: str,
        token: str,
        model: ResponseModel,
        condition: str,
        rng: random.Random,
        attention: dict[str, str],
    ) -> None:
        self._client = http_client(url, timeout=15.0, headers={"Authorization": f"Bearer {token}"})
        self.model = model
        self.condition = condition
        self.rng = rng
        self.attention = attention

    def _answers(self, page: dict[str, Any]) -> dict[str, Any]:
        return questionnaire_answers(page, self.model, self.condition, self.rng, self.attention)

    async def _send(self, method: str, path: str, body: Any = None) -> dict[str, Any]:
        response = await self._client.request(method, path, json=body)
        payload: dict[str, Any] = response.json()
        if response.status_code != 200:
            raise ApiError(response.status_code, str(payload.get("detail")))
        return payload

    async def fill(self) -> int:
        """Answer pages until the tablet says wait or done; returns how many it submitted."""
        submitted = 0
        page = await self._send("GET", "/api/v1/tablet")
        while page["kind"] in ("language", "consent", "questionnaire"):
            if page["kind"] == "language":
                chosen = self.rng.choice([offered["code"] for offered in page["languages"]])
                page = await self._send("POST", "/api/v1/tablet/language", {"language": chosen})
                continue
            if page["kind"] == "consent":
                page = await self._send("POST", "/api/v1/tablet/consent", {"accept": True})
            else:
                page = await self._send(
                    "POST",
                    f"/api/v1/tablet/questionnaires/{page['instrument']['key']}",
                    {"session": page["session"], "answers": self._answers(page)},
                )
            submitted += 1
        return submitted

    async def aclose(self) -> None:
        await self._client.aclose()


class _Lane:
    """One bot station, taking participants one after another."""

    def __init__(
        self,
        config: BotConfig,
        station: str,
        experimenter: ExperimenterClient,
        robot: _Robot,
        categories: list[_Category],
        rng: random.Random,
        summary: BotSummary,
        tick: Callable[[], None],
        attention: dict[str, str],
    ) -> None:
        self.config = config
        self.station = station
        self.experimenter = experimenter
        self.robot = robot
        self.categories = categories
        self.attention = attention
        self.rng = rng
        self.summary = summary
        self.tick = tick

    async def run_participant(self) -> None:
        enrolled = await self.experimenter.enroll(self.config.study, language=self.config.language)
        code = str(enrolled["code"])
        self.summary.participants += 1
        link = await self.experimenter.call(
            "POST", f"/studies/{self.config.study}/participants/{code}/link"
        )
        tablet = _Tablet(
            self.config.url,
            link["token"],
            self.config.responses,
            str(enrolled["condition"]),
            self.rng,
            self.attention,
        )
        preferred = preferences(self.categories, self.rng)
        try:
            # Inside the try: a run stopped while the seating's response is on its way (the
            # server has seated the participant) still frees the station.
            await _to_its_end(self.experimenter.assign(self.station, self.config.study, code))
            while True:
                submitted = await tablet.fill()  # await first: += would read before the await
                self.summary.questionnaires += submitted
                state = await self.experimenter.station_state(self.station)
                expected = state["expected"]
                if expected["action"] == "done":
                    self.summary.completed += 1
                    return
                if expected["action"] != "start_session":
                    raise ApiError(409, f"{code}: unexpected state: {expected['message']}")
                started = await _to_its_end(self.experimenter.start_session(self.station))
                await self._run_session(started.expected.categories, preferred)
                self.summary.sessions += 1
        finally:
            # Carried to its end: a stopping run cancels its lanes a second time (run_bots'
            # cleanup), which would otherwise cut this one short and leave the participant seated.
            await _to_its_end(self._clean_up(tablet, code))

    async def _clean_up(self, tablet: _Tablet, code: str) -> None:
        """Close the participant's tablet and free the station; a failure to free it is recorded
        beside the lane's own error (if any), which goes on as it was."""
        await tablet.aclose()
        try:
            await self._leave_station(code)
        except (ApiError, ConnectionError, TimeoutError, OSError, httpx.HTTPError) as exc:
            self.summary.errors.append(f"{self.station}: {code} was left seated: {exc}")

    async def _leave_station(self, code: str) -> None:
        """Free the bot station of participant ``code``, also when the run is stopped
        mid-session (Ctrl-C, a failed lane): the session is ended early, as an experimenter
        would, so that the next run finds the station free instead of a participant it may not
        unseat. Someone else seated there (the seating was refused) is left alone."""
        for _ in range(LEAVE_ATTEMPTS):
            state = await self.experimenter.station_state(self.station)
            if state.get("participant") != code:
                return
            session = state.get("session") or {}
            try:
                if session.get("status") == "running":
                    await self.experimenter.end_session(self.station)
                await self.experimenter.unassign(self.station)
                return
            except ApiError as exc:
                # A request the stopped lane still had in flight (its last answer, ending the
                # session) reached the server in between: look again, as an experimenter would.
                if exc.status != 409:
                    raise
        raise ApiError(409, f"{code} could not be unseated from {self.station}")

    async def _run_session(self, categories: list[str], preferred: dict[str, int]) -> None:
        await answer_session(
            self.robot,
            categories,
            preferred,
            rng=self.rng,
            noise=self.config.noise,
            on_step=self._answered,
        )

    def _answered(self) -> None:
        self.summary.steps += 1
        self.tick()


async def answer_session(
    robot: _Robot,
    categories: list[str],
    preferred: dict[str, int],
    *,
    rng: random.Random,
    noise: float,
    on_step: Callable[[], None] = lambda: None,
    think: Callable[[], Awaitable[None]] | None = None,
    walk: Callable[[], Awaitable[None]] | None = None,
) -> int:
    """Answer runs until the session is over, as the paper's rules say (``noise``: the chance of
    answering against them); each run visits its categories in a new order. ``walk`` is awaited
    before each question and ``think`` before each answer (a person's pace). Returns how many
    steps were answered."""
    pending = list(categories)
    steps = 0
    while True:
        order = list(pending)
        rng.shuffle(order)
        for category in order:
            if walk is not None:
                await walk()
            step = await robot.prompt(category)
            says_yes = step.action == preferred[category]
            if rng.random() < noise:
                says_yes = not says_yes
            if think is not None:
                await think()
            reply = await robot.answer(step.step_id, "yes" if says_yes else "no")
            steps += 1
            on_step()
            if reply.expected.action != "prompt":
                return steps
            if reply.run_completed:
                pending = reply.expected.categories
                break


T = TypeVar("T")

LEAVE_ATTEMPTS = 3
"""How often a stopping lane looks at its station again when freeing it was refused because the
station changed in between (a request of the lane's still on its way)."""
SETTLE_SECONDS = 15.0
"""How long a stopped run waits for a seating or session start in flight to be answered: one
request's timeout. A server that has not answered by then is not waited for any longer."""


async def _to_its_end(call: Awaitable[T], settle: float = SETTLE_SECONDS) -> T:
    """Await a request that seats or starts (or a lane's cleanup) to its response, even when
    the run is stopped meanwhile (for at most ``settle`` seconds more), and only then stop
    (re-raise the cancellation).

    A request cancelled in flight may still be carried out by the server after the lane's
    cleanup has looked at the station and found it free: the participant would stay seated.
    Waiting for the answer lets the cleanup see what the server did."""
    task = asyncio.ensure_future(call)
    deadline: float | None = None
    while not task.done():
        remaining = None if deadline is None else deadline - time.monotonic()
        if remaining is not None and remaining <= 0 and not task.cancelling():
            task.cancel()  # the server is not answering: stop waiting, once the task has stopped
        try:
            await asyncio.wait({task}, timeout=None if task.cancelling() else remaining)
        except asyncio.CancelledError:  # asyncio.wait leaves the task running
            if deadline is None:
                deadline = time.monotonic() + settle
    if deadline is not None:
        raise asyncio.CancelledError
    return task.result()


class BotStationsBusy(Exception):
    """A bot station cannot be the bots': someone is seated there (another bots run uses it, or
    one stopped hard left its participant), or it has device keys of its own (a lab's robot or
    room). Found before anyone is enrolled, so a refused run adds no participant to the study
    (enrolling randomises)."""


BOT_KEY_LABEL = "bots"
"""The label of the device keys the bots issue (and revoke when they stop)."""


async def _claim_stations(admin: ExperimenterClient, names: list[str]) -> None:
    """Create the bot stations that do not exist yet; refuse the run if one is not free for
    bots."""
    existing = {s["name"]: s for s in await admin.call("GET", "/stations")}
    other_prefix = "or give this run other stations with --station-prefix"
    for name in names:
        found = existing.get(name)
        if found is None:
            await admin.ensure_station(name)
            continue
        keys = sorted(
            {
                d["label"]
                for d in found.get("devices", [])
                if d.get("revoked_at") is None and d["label"] != BOT_KEY_LABEL
            }
        )
        if keys:
            raise BotStationsBusy(
                f"station {name} has device keys of its own ({', '.join(keys)}): bots use "
                f"stations of their own; {other_prefix}"
            )
        if found.get("participant"):
            raise BotStationsBusy(
                f"station {name} already has participant {found['participant']} seated "
                "(another bots run, or one stopped hard): end their session and unseat them on "
                f"the station's console, {other_prefix}"
            )


def check_config(config: BotConfig) -> None:
    """ValueError for a run that cannot be: no lanes, negative participants, noise outside 0–1."""
    if config.participants < 0 or config.concurrency < 1:
        raise ValueError("participants must be ≥ 0 and concurrency ≥ 1")
    if not 0.0 <= config.noise <= 1.0:
        raise ValueError("noise must lie in [0, 1]")


async def run_bots(config: BotConfig, *, tick: Callable[[], None] = lambda: None) -> BotSummary:
    """Drive ``config.participants`` simulated participants through the study."""
    check_config(config)
    started = time.perf_counter()
    summary = BotSummary()
    rng = random.Random(config.seed)
    async with ExperimenterClient(config.url) as admin:
        await admin.sign_in(config.username, config.password)
        protocol = await admin.protocol(config.study)
        categories = categories_of(protocol)
        attention = attention_answers(protocol)
        queue: asyncio.Queue[int] = asyncio.Queue()
        for index in range(config.participants):
            queue.put_nowait(index)

        issuing: list[asyncio.Future[IssuedDeviceOut]] = []

        lanes = min(config.concurrency, max(config.participants, 1))
        await _claim_stations(admin, [f"{config.station_prefix}-{n}" for n in range(1, lanes + 1)])

        async def lane_worker(number: int, lane_rng: random.Random) -> None:
            station = f"{config.station_prefix}-{number}"
            # Shielded and remembered: even if the run is cancelled while the key is being
            # issued, the cleanup learns the key's id and revokes it.
            issue = asyncio.ensure_future(admin.issue_key(station, BOT_KEY_LABEL))
            issuing.append(issue)
            key = (await asyncio.shield(issue)).key
            if config.transport == "ws":
                socket = StationSocket(config.url, key)
                await socket.open()
                robot = _Robot(None, socket)
            else:
                robot = _Robot(RobotClient(config.url, key), None)
            lane = _Lane(
                config, station, admin, robot, categories, lane_rng, summary, tick, attention
            )
            try:
                while not queue.empty():
                    queue.get_nowait()
                    try:
                        await lane.run_participant()
                    except (
                        ApiError,
                        ConnectionError,
                        TimeoutError,
                        OSError,
                        httpx.HTTPError,
                    ) as exc:
                        summary.errors.append(f"{station}: {exc}")
            finally:
                await robot.close()

        workers = [
            asyncio.ensure_future(lane_worker(n, random.Random(rng.random())))
            for n in range(1, lanes + 1)
        ]
        try:
            await asyncio.gather(*workers)
        finally:
            # Success, a failed lane or cancellation (Ctrl-C): stop every lane, then revoke.
            for worker in workers:
                worker.cancel()
            await asyncio.gather(*workers, return_exceptions=True)
            await _revoke_keys(admin, issuing, summary)
    summary.seconds = round(time.perf_counter() - started, 3)
    return summary


async def _revoke_keys(
    admin: ExperimenterClient, issuing: list[asyncio.Future[IssuedDeviceOut]], summary: BotSummary
) -> None:
    """Revoke every device key this run issued; a key that cannot be revoked is an error."""
    for issued in await asyncio.gather(*issuing, return_exceptions=True):
        if not isinstance(issued, IssuedDeviceOut):
            continue  # never issued
        try:
            await admin.revoke_key(issued.id)
        except (ApiError, httpx.HTTPError, OSError) as exc:
            if isinstance(exc, ApiError) and exc.status == 409:
                continue  # already revoked
            summary.errors.append(f"{issued.station}: device key {issued.id} not revoked: {exc}")
