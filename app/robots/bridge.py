"""The loop that joins a robot to a station: the robot asks, listens, and says the reply.

A bridge is a robot client like any other (the station WebSocket authenticated by its
``Authorization: Bearer`` header, as docs/robot-integration.md §5 prefers; idempotency keys), so
the server needs nothing special for it. What it adds is the robot's side:

- a question is asked when the trigger says so: the participant stepping into a zone (the room's
  presence), the robot's own cue, or only the operator console's "ask now" (a Wizard-of-Oz prompt,
  which every trigger also follows);
- the robot says the question, listens for the study's yes/no phrases, and asks again on silence
  or anything unclear, up to the study's limit; then the console is asked for a Wizard-of-Oz
  answer, and the robot says the reply to whichever answer is recorded;
- an answer is sent with the recogniser's words and confidence, under one idempotency key however
  often it is retried, and the reply is said only once the server has recorded it: an answer the
  participant heard acknowledged is never lost, and none is sent twice; a reply the robot was
  cut off in (lost while saying it), like the reply to an answer the console gave while the robot
  was away, is said once the robot is back, before anything else, or, if the study has moved on
  meanwhile, told to the console (never said out of turn, never dropped unsaid without a word);
- a recogniser's confidence outside 0-1 (85 for 85 %) is refused in one line, never clamped into
  a certain answer;
- losing the robot or the server is told to the console (or shown there as the device
  disconnected), and the bridge reconnects and asks the open question again.

Work is done one item at a time (a robot does one thing at a time); the robot's blocking calls run
in worker threads, each bounded by the robot adapter.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import httpx

from app.api.runtime_schemas import PromptOut, SpeechOut
from app.client import (
    ApiError,
    DeviceKeyRefused,
    RobotClient,
    StationSocket,
    backoff_delays,
)
from app.robots.robot import (
    Colour,
    Heard,
    Robot,
    RobotError,
    RobotLost,
    RobotUnreachable,
    colour_of,
)
from app.robots.triggers import Trigger  # here too: the bridge's users import it from here
from app.speech.vocabulary import Vocabulary

T = TypeVar("T")

CONFLICT = 409
SERVER_ERROR = 500
SERVER_AWAY = (ConnectionError, TimeoutError, OSError, httpx.HTTPError)
"""What a request raises when the server cannot be reached (the WebSocket's and httpx's)."""
TRANSCRIPT_MAX = 200


TRIGGER_WAITS = {
    Trigger.PRESENCE: "the participant to step into a zone of the room",
    Trigger.ROBOT: "the robot's own cue",
    Trigger.CONSOLE: 'the operator console\'s "ask now"',
}


class BridgeRefused(Exception):
    """The bridge cannot start: one line saying why (a refused key, the wrong station, a server
    or robot out of reach). Nothing has been sent to the study."""


@dataclass(frozen=True)
class BridgeSettings:
    """Where the bridge connects and what triggers questions."""

    url: str
    station: str
    key: str
    trigger: Trigger = Trigger.PRESENCE
    retry_delay: float = 0.5
    max_retry_delay: float = 10.0
    cue_poll_seconds: float = 1.0
    request_timeout: float = 15.0
    speaks: str = "en"
    """The participants' language the robot is set up to speak and hear (its voice and
    recogniser options): a participant in another language is not spoken to in the wrong one."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "trigger", Trigger(self.trigger))  # "robot" as Trigger.ROBOT


@dataclass(frozen=True)
class _Ask:
    """Prompt this category (the trigger fired), then handle the step."""

    category: str | None
    why: str


@dataclass(frozen=True)
class _Handle:
    """Ask an open step's question (a console's prompt, or one left open by a restart)."""

    step_id: int
    cut_off: PromptOut | None = None
    """The prompt, when the robot was lost while asking it: if the console answered it while
    the robot was away, its reply is said (or told to the console) instead."""


@dataclass(frozen=True)
class _Unsaid:
    """A recorded answer's reply the robot has not finished saying (it was lost meanwhile)."""

    step_id: int
    question: str
    participant: str | None
    reply: str
    gesture: str | None
    leds: Colour | None
    answered_while_away: bool = False
    """The console answered while the robot was away (else: the robot was lost replying)."""


@dataclass
class _Answered:
    """What the bridge knows of steps answered while it listened (Wizard-of-Oz answers)."""

    replies: dict[int, tuple[str, str | None]] = field(default_factory=dict)
    changed: asyncio.Condition = field(default_factory=asyncio.Condition)


def confidence_of(heard: Heard) -> float | None:
    """The recogniser's confidence as a finite number, or None when it is none."""
    try:
        confidence = float(heard.confidence)
    except (TypeError, ValueError):
        return None
    return confidence if math.isfinite(confidence) else None


def out_of_range(heard: Heard | None) -> bool:
    """A confidence that is a number outside 0-1 (a node reporting 85 for 85 %): refused, not
    clamped, since 1.0 would pass any ``min_confidence`` as certain."""
    if heard is None:
        return False
    confidence = confidence_of(heard)
    return confidence is not None and not 0.0 <= confidence <= 1.0


def clean_transcript(heard: Heard | None) -> tuple[str | None, float | None]:
    """The recogniser's words and confidence as the server stores them: printable, at most 200
    characters, a confidence in [0, 1]; None for what cannot be stored (a recogniser may return
    anything; one outside 0-1 is refused before an answer is sent, see :func:`out_of_range`)."""
    if heard is None:
        return None, None
    printable = "".join(ch if ch.isprintable() else " " for ch in str(heard.words))
    words = " ".join(printable.split())[:TRANSCRIPT_MAX] or None
    confidence = confidence_of(heard)
    if confidence is not None and not 0.0 <= confidence <= 1.0:
        confidence = None
    return words, confidence


def describe_heard(heard: Heard | None) -> str:
    """How the bridge's log names what was heard."""
    words, confidence = clean_transcript(heard)
    if words is None:
        return "silence"
    if heard is not None and out_of_range(heard):
        return f"“{words}” (confidence {confidence_of(heard):g}, not within 0-1)"
    return f"“{words}” ({confidence:.2f})" if confidence is not None else f"“{words}”"


class Bridge:
    """One robot at one station, until :meth:`stop` (or Ctrl-C)."""

    def __init__(
        self, robot: Robot, settings: BridgeSettings, *, say: Callable[[str], None] = print
    ) -> None:
        self.robot = robot
        self.settings = settings
        self._log = say
        self._socket = StationSocket(
            settings.url,
            settings.key,
            request_timeout=settings.request_timeout,
            retry_delay=settings.retry_delay,
            max_retry_delay=settings.max_retry_delay,
        )
        self._client = RobotClient(settings.url, settings.key, timeout=settings.request_timeout)
        self._work: asyncio.Queue[_Ask | _Handle] = asyncio.Queue()
        self._asked: set[int] = set()
        self._answered = _Answered()
        self._unsaid: dict[int, _Unsaid] = {}
        """Replies recorded but not yet said in full: said once the robot is back (before
        anything else), or told to the console if the study has moved on meanwhile."""
        self._missed_reply_shown = False
        self._speech: SpeechOut | None = None
        """The speech settings of the question asked last (its reply's gesture and LEDs)."""
        self._stopping = asyncio.Event()
        self._robot_back = asyncio.Lock()
        self._rng = random.Random()

    # -- start and stop ---------------------------------------------------------------------

    async def start(self) -> None:
        """Join the station and reach the robot, or raise :class:`BridgeRefused` (one line)."""
        url = self.settings.url
        try:
            await self._socket.open()
        except DeviceKeyRefused as refused:
            raise BridgeRefused(f"the server at {url} refused the key: {refused.reason}") from None
        except ApiError as exc:
            raise BridgeRefused(f"the server at {url} refused the bridge: {exc.detail}") from None
        except (OSError, TimeoutError, ConnectionError) as exc:
            raise BridgeRefused(
                f"cannot reach the trustlab server at {url}: {exc or type(exc).__name__}"
            ) from None
        except Exception as exc:  # a URL that is not a trustlab server (wrong path, not HTTP)
            raise BridgeRefused(f"cannot join the station at {url}: {exc}") from None
        state = self._socket.state or {}
        if state.get("station") != self.settings.station:
            await self.close()
            raise BridgeRefused(
                f"the key belongs to station {state.get('station')!r}, not "
                f"{self.settings.station!r}: use that station's key"
            )
        try:
            await asyncio.to_thread(self.robot.connect)
        except RobotError as exc:
            await self.close()
            raise BridgeRefused(str(exc)) from None
        await self._notice(None)
        self._log(
            f"Bridge: {self.robot.description} joined station {self.settings.station} at {url}; "
            f"waiting for {TRIGGER_WAITS[self.settings.trigger]}. Ctrl-C stops it."
        )

    async def run(self) -> None:
        """Serve until :meth:`stop`: events, the robot's cues and the work they bring."""
        self._queue_open_prompts(self._socket.state)
        tasks = [
            asyncio.create_task(self._follow_events()),
            asyncio.create_task(self._do_work()),
        ]
        if self.settings.trigger is Trigger.ROBOT:
            tasks.append(asyncio.create_task(self._follow_cues()))
        stopping = asyncio.create_task(self._stopping.wait())
        try:
            done, _ = await asyncio.wait([*tasks, stopping], return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if task is not stopping:
                    task.result()  # a refused key ends the bridge with its reason
        finally:
            for task in [*tasks, stopping]:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task

    def stop(self) -> None:
        """Ask :meth:`run` to return."""
        self._stopping.set()

    async def close(self) -> None:
        """Leave the station and release the robot."""
        with contextlib.suppress(Exception):
            await self._socket.close()
        with contextlib.suppress(Exception):
            await self._client.aclose()
        with contextlib.suppress(Exception):
            await asyncio.to_thread(self.robot.close)

    # -- what makes the robot ask -------------------------------------------------------------

    def _queue_open_prompts(self, state: dict[str, Any] | None) -> None:
        for prompt in (state or {}).get("open_prompts", []):
            self._work.put_nowait(_Handle(int(prompt["step_id"])))

    async def _follow_events(self) -> None:
        while True:
            event = await self._socket.next_event()
            kind, data = event.get("type"), event.get("data") or {}
            if kind == "reconnected":
                self._log("Bridge: back in touch with the server.")
                state = event.get("state") or {}
                self._queue_open_prompts(state)
                if state.get("last_reply"):  # answered on the console while we were away
                    await self._note_reply(state["last_reply"])
            name = event.get("event")
            if name == "prompt_opened":
                self._work.put_nowait(_Handle(int(data["step_id"])))
            elif name == "answer_recorded":
                await self._note_reply(data)
            elif name == "zone_entered" and self.settings.trigger is Trigger.PRESENCE:
                zone = str(data.get("zone"))
                self._work.put_nowait(_Ask(zone, f"the participant stepped into zone {zone}"))
            async with self._answered.changed:
                self._answered.changed.notify_all()  # the state moved on: waiters look again

    async def _note_reply(self, data: dict[str, Any]) -> None:
        """Keep a recorded answer's reply for whoever waits to say it (an answer_recorded push,
        or the state's last_reply after a reconnection that missed the push)."""
        async with self._answered.changed:
            self._answered.replies[int(data["step_id"])] = (
                str(data.get("reply", "")),
                data.get("confidence"),
            )
            self._answered.changed.notify_all()

    async def _follow_cues(self) -> None:
        while True:
            try:
                cue = await asyncio.to_thread(self.robot.wait_cue, self.settings.cue_poll_seconds)
            except RobotLost as lost:
                await self._reconnect_robot(lost)
                continue
            if cue is not None:
                self._work.put_nowait(_Ask(cue.category, cue.source or "the robot's cue"))

    # -- the work -----------------------------------------------------------------------------

    async def _do_work(self) -> None:
        delays = backoff_delays(self.settings.retry_delay, self.settings.max_retry_delay, self._rng)
        while True:
            unsaid = next(iter(self._unsaid.values()), None)
            item = _Handle(unsaid.step_id) if unsaid else await self._work.get()
            prompt: PromptOut | None = None
            try:
                if unsaid is not None:
                    await self._say_unsaid(unsaid)
                    continue
                prompt = await self._prompt_for(item)
                if prompt is not None:
                    await self._ask(prompt)
                elif isinstance(item, _Handle) and item.cut_off is not None:
                    self._answered_while_away(item.cut_off)  # answered after the robot was back
            except RobotLost as lost:
                await self._reconnect_robot(lost)
                if unsaid is None and prompt is not None and prompt.step_id in self._unsaid:
                    continue  # answered, its reply cut off: said first (above), not asked again
                if unsaid is None and prompt is not None and self._answered_while_away(prompt):
                    continue  # the console answered meanwhile: its reply first (above)
                if unsaid is None:
                    again = item if prompt is None else _Handle(prompt.step_id, prompt)
                    self._work.put_nowait(again)
            except DeviceKeyRefused:
                raise
            except ApiError as exc:
                if exc.status < SERVER_ERROR:
                    self._log(f"Bridge: the server refused: {exc.detail}")
                    continue
                await self._retry_later(None if unsaid else item, prompt, exc.detail, next(delays))
            except SERVER_AWAY as exc:
                why = str(exc) or type(exc).__name__
                await self._retry_later(None if unsaid else item, prompt, why, next(delays))
            else:
                delays = backoff_delays(
                    self.settings.retry_delay, self.settings.max_retry_delay, self._rng
                )

    async def _retry_later(
        self, item: _Ask | _Handle | None, prompt: PromptOut | None, why: str, delay: float
    ) -> None:
        """The server could not be reached or was busy: the question is asked once it answers
        (a prompt already drawn is asked as it is; nothing is drawn twice). ``item`` None: an
        unsaid reply, which stays first in line anyway."""
        self._log(f"Bridge: lost the server ({why}); trying again.")
        if prompt is not None:
            self._asked.discard(prompt.step_id)
            item = _Handle(prompt.step_id)
        await asyncio.sleep(delay)
        if item is not None:
            self._work.put_nowait(item)

    async def _prompt_for(self, item: _Ask | _Handle) -> PromptOut | None:
        """The open step to ask, or None when there is nothing (left) to ask."""
        if isinstance(item, _Handle):
            if item.step_id in self._asked:
                return None
            state = await self._fresh_state()
            for open_prompt in state.get("open_prompts", []):
                if int(open_prompt["step_id"]) == item.step_id:
                    return PromptOut.model_validate(open_prompt)
            return None
        category = item.category
        if category is None:
            expected = (await self._fresh_state()).get("expected", {})
            if expected.get("action") not in ("prompt", "answer") or not expected.get("categories"):
                self._log(f"Bridge: {item.why}, but the station expects no question now.")
                return None
            category = str(expected["categories"][0])
        self._log(f"Bridge: {item.why}: asking for {category}.")
        prompt = await self._socket.prompt(category)
        return None if prompt.step_id in self._asked else prompt

    async def _fresh_state(self) -> dict[str, Any]:
        return (await self._socket.current_state()).model_dump(mode="json")

    async def _ask(self, prompt: PromptOut) -> None:
        """Say the question, listen until an answer counts, send it, say the reply."""
        self._asked.add(prompt.step_id)
        if prompt.language != self.settings.speaks:
            await self._cannot_speak(prompt)
            return
        speech = self._speech = await self._client.speech()
        vocabulary = Vocabulary.of(speech.yes, speech.no, speech.min_confidence)
        await self._robot(self.robot.say, prompt.question, None)
        self._log(f"Robot asks (step {prompt.step_id}): {prompt.question}")
        heard: Heard | None = None
        for attempt in range(1, speech.attempts + 1):
            if await self._say_recorded_reply(prompt, speech):
                return
            heard = await self._robot(self.robot.listen, vocabulary.phrases, speech.listen_seconds)
            if out_of_range(heard):
                self._log(
                    f"Bridge: the robot's recogniser reported {describe_heard(heard)}: a "
                    "confidence is a fraction from 0 to 1 (0.85 for 85 %); not taken as an answer."
                )
            answer = None if out_of_range(heard) else vocabulary.classify(heard)
            self._log(f"Robot heard: {describe_heard(heard)} -> {answer or 'unclear'}")
            if await self._say_recorded_reply(prompt, speech):
                return  # answered on the console meanwhile: that answer stands
            if answer is not None:
                await self._send(prompt, answer, heard, speech)
                return
            if attempt < speech.attempts:
                await self._robot(self.robot.say, speech.reprompt, None)
                self._log(f"Robot asks again: {speech.reprompt}")
        await self._ask_the_wizard(prompt, heard, speech)

    async def _send(
        self, prompt: PromptOut, answer: str, heard: Heard | None, speech: SpeechOut
    ) -> None:
        """Send the answer under one key until the server has it, then say the reply."""
        key = uuid.uuid4().hex
        delays = backoff_delays(self.settings.retry_delay, self.settings.max_retry_delay, self._rng)
        while True:
            try:
                out = await self._socket.answer(
                    prompt.step_id,
                    "yes" if answer == "yes" else "no",
                    idempotency_key=key,
                    heard=clean_transcript(heard),
                )
                break
            except ApiError as exc:
                if exc.status == CONFLICT and await self._say_recorded_reply(
                    prompt, speech, wait=True
                ):
                    return  # someone else's answer was recorded first: say its reply
                if exc.status < SERVER_ERROR:
                    raise
                self._log(f"Bridge: the server is busy ({exc.detail}); retrying.")
                await asyncio.sleep(next(delays))
            except SERVER_AWAY as exc:
                self._log(f"Bridge: lost the server ({exc or type(exc).__name__}); retrying.")
                await asyncio.sleep(next(delays))
        await self._say_reply(prompt, out.reply, out.confidence, speech)
        self._log(f"Robot replies ({out.confidence}): {out.reply}")

    async def _say_reply(
        self, prompt: PromptOut, reply: str, level: str | None, speech: SpeechOut
    ) -> None:
        """Say a recorded answer's reply, with the protocol's gesture and LED colour for its
        level (if any); kept until said, so that a robot lost while saying it says it once it is
        back (:meth:`_say_unsaid`)."""
        await self._say_kept(self._kept(prompt, reply, level, speech))

    def _kept(
        self,
        prompt: PromptOut,
        reply: str,
        level: str | None,
        speech: SpeechOut | None,
        *,
        answered_while_away: bool = False,
    ) -> _Unsaid:
        """A reply to keep until said, with its level's gesture and LED colour (if any)."""
        seated = (self._socket.state or {}).get("participant")
        leds = speech.leds.get(level or "") if speech is not None else None
        return _Unsaid(
            prompt.step_id,
            prompt.question,
            seated,
            reply,
            speech.gestures.get(level or "") if speech is not None else None,
            colour_of(leds) if leds else None,
            answered_while_away,
        )

    def _answered_while_away(self, prompt: PromptOut) -> bool:
        """The robot was lost while asking ``prompt``: if the console answered it meanwhile,
        keep that reply as unsaid, so that it is said once the robot is back or, if the study
        has moved on by then, told to the console (:meth:`_say_unsaid`). True when kept."""
        recorded = self._answered.replies.get(prompt.step_id)
        if recorded is None or prompt.step_id in self._unsaid:
            return False
        reply, level = recorded
        self._unsaid[prompt.step_id] = self._kept(
            prompt, reply, level, self._speech, answered_while_away=True
        )
        return True

    async def _say_kept(self, unsaid: _Unsaid) -> None:
        self._unsaid[unsaid.step_id] = unsaid
        await self._robot(self.robot.say, unsaid.reply, unsaid.gesture, unsaid.leds)
        self._unsaid.pop(unsaid.step_id, None)
        if self._missed_reply_shown:
            self._missed_reply_shown = False
            await self._notice(None)

    async def _say_unsaid(self, unsaid: _Unsaid) -> None:
        """The robot was lost while saying this reply and is back: say it now, unless the study
        has moved on meanwhile (another question asked or answered, another participant seated);
        then the console is told what the participant did not hear."""
        state = await self._fresh_state()
        later_asked = any(int(p["step_id"]) != unsaid.step_id for p in state["open_prompts"])
        async with self._answered.changed:
            later_answered = any(step > unsaid.step_id for step in self._answered.replies)
        moved_on = later_asked or later_answered or state.get("participant") != unsaid.participant
        who = unsaid.participant or "the participant"
        if not moved_on:
            if unsaid.answered_while_away:
                self._log(
                    f"Bridge: saying the reply to the console's answer given while the robot was "
                    f"away (step {unsaid.step_id})."
                )
            else:
                self._log(
                    f"Bridge: saying the reply the robot was cut off in (step {unsaid.step_id})."
                )
            await self._say_kept(unsaid)
            self._log(f"Robot replies: {unsaid.reply}")
            return
        self._unsaid.pop(unsaid.step_id, None)
        what = (
            f"the robot was away when {who}'s answer to “{unsaid.question}” was given on this "
            "console,"
            if unsaid.answered_while_away
            else f"the robot was lost while replying to {who}'s answer to “{unsaid.question}”"
        )
        line = (
            f"{what} and the study has moved on: the reply “{unsaid.reply}” was recorded but "
            "not heard"
        )
        await self._notice(line[:300], attention=True)
        self._missed_reply_shown = True
        self._log(f"Bridge: {line}.")

    async def _say_recorded_reply(
        self, prompt: PromptOut, speech: SpeechOut, *, wait: bool = False
    ) -> bool:
        """If this step has been answered by someone else (the console), say that reply."""
        step_id = prompt.step_id
        async with self._answered.changed:
            if wait and step_id not in self._answered.replies:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(
                        self._answered.changed.wait_for(lambda: step_id in self._answered.replies),
                        self.settings.request_timeout,
                    )
            recorded = self._answered.replies.get(step_id)
        if recorded is None:
            return False
        reply, level = recorded
        await self._say_reply(prompt, reply, level, speech)
        self._log(f"Robot replies to the console's answer: {reply}")
        return True

    async def _ask_the_wizard(
        self, prompt: PromptOut, heard: Heard | None, speech: SpeechOut
    ) -> None:
        """Tell the console the answer stayed unclear; say the reply once it gives one."""
        await self._wait_for_the_console(
            prompt,
            f"{self._participant()}'s answer to “{prompt.question}” stayed unclear after "
            f"{speech.attempts} tries (last heard: {describe_heard(heard)}): give a "
            "Wizard-of-Oz answer on this console",
        )
        await self._say_recorded_reply(prompt, speech)

    async def _cannot_speak(self, prompt: PromptOut) -> None:
        """The participant's language is not the robot's: nothing is said (a question in the
        wrong voice, or a recogniser listening for the wrong words, would not be the study's),
        and the console is asked for a Wizard-of-Oz answer."""
        await self._wait_for_the_console(
            prompt,
            f"{self._participant()} takes part in {prompt.language!r}, but this robot speaks "
            f"{self.settings.speaks!r}: ask “{prompt.question}” and give a Wizard-of-Oz answer "
            f"on this console, or restart the bridge with --speaks {prompt.language} and the "
            "robot's voice for it",
        )

    def _participant(self) -> str:
        return str((self._socket.state or {}).get("participant") or "the participant")

    async def _wait_for_the_console(self, prompt: PromptOut, line: str) -> None:
        """Put ``line`` on the console as a notice that needs the operator, until the step is
        answered there (or is no longer open); then clear it."""
        await self._notice(line[:300], attention=True)
        self._log(f"Bridge: {line}.")

        def settled() -> bool:
            if prompt.step_id in self._answered.replies:
                return True
            open_steps = {p["step_id"] for p in (self._socket.state or {}).get("open_prompts", [])}
            return prompt.step_id not in open_steps  # ended early, withdrawn, seat freed

        async with self._answered.changed:
            await self._answered.changed.wait_for(settled)
        await self._notice(None)

    # -- the robot and the console ------------------------------------------------------------

    async def _robot(self, method: Callable[..., T], *args: Any) -> T:
        return await asyncio.to_thread(method, *args)

    async def _reconnect_robot(self, lost: RobotLost) -> None:
        """Tell the console, then reconnect to the robot until it answers again. The worker and
        the cue watcher may both notice the loss: the second waits for the first's reconnection."""
        if self._robot_back.locked():
            async with self._robot_back:
                return
        async with self._robot_back:
            await self._reconnect(lost)

    async def _reconnect(self, lost: RobotLost) -> None:
        self._log(f"Bridge: lost {self.robot.description} ({lost}); reconnecting.")
        await self._notice(f"lost the robot ({lost}); reconnecting", attention=True)
        delays = backoff_delays(self.settings.retry_delay, self.settings.max_retry_delay, self._rng)
        while True:
            await asyncio.sleep(next(delays))
            with contextlib.suppress(Exception):
                await asyncio.to_thread(self.robot.close)
            try:
                await asyncio.to_thread(self.robot.connect)
            except (RobotLost, RobotUnreachable):
                continue
            break
        self._asked.clear()  # the open question was cut off: ask it again
        await self._notice(None)
        self._log(f"Bridge: {self.robot.description} is back.")

    async def _notice(self, text: str | None, *, attention: bool = False) -> None:
        """A line on the console; the bridge goes on if the server cannot take it."""
        try:
            await self._client.notice(text, attention=attention)
        except (ApiError, *SERVER_AWAY) as exc:
            self._log(f"Bridge: could not update the console ({exc or type(exc).__name__})")
