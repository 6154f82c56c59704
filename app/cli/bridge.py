"""``trustlab bridge naoqi|furhat|rosbridge``: join a physical robot to a station.

Each kind builds its robot adapter from its own options (app/robots/naoqi.py, furhat.py,
rosbridge.py) and hands it to the one bridge loop (app/robots/bridge.py). The vendor clients are
the ``robots`` extra: a missing one is one line saying what to install, not a traceback.
"""

from __future__ import annotations

import contextlib
import importlib
import signal
import sys
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.cli.errors import fail
from app.robots.triggers import Trigger

if TYPE_CHECKING:
    from app.robots.bridge import BridgeSettings
    from app.robots.robot import Robot


bridge = typer.Typer(
    help="Join a physical robot (NAOqi, Furhat, ROS 2 through rosbridge) to a station: it says "
    "each question, hears the yes/no answer and says the reply (docs/robots.md).",
    no_args_is_help=True,
)

INSTALL_HINT = "pip install -r requirements-robots.lock (or pip install 'trustlab[robots]')"

Url = Annotated[str, typer.Option(help="The trustlab server, e.g. http://127.0.0.1:8000.")]
StationName = Annotated[str, typer.Option(help="The station the robot stands at.")]
Key = Annotated[
    str,
    typer.Option(
        envvar="TRUSTLAB_DEVICE_KEY",
        help="The station's device key (tlk_…); or set TRUSTLAB_DEVICE_KEY, which keeps it out "
        "of the process list.",
    ),
]
TriggerOption = Annotated[
    Trigger,
    typer.Option(
        help="What makes the robot ask: presence (the participant steps into a zone of the "
        "room), robot (the robot's own cue) or console (only the console's ask now, which "
        "every trigger also follows)."
    ),
]
Host = Annotated[str, typer.Option(help="The robot's address.")]
Language = Annotated[str, typer.Option(help="The language the robot speaks and listens in.")]
Speaks = Annotated[
    str,
    typer.Option(
        help="The participants' language the robot's voice and recogniser are set up for (a "
        "study language code such as en or sv); a participant in another is left to the "
        "console's Wizard-of-Oz answer."
    ),
]
Voice = Annotated[
    str | None, typer.Option(help="One of the robot's voices (default: its current voice).")
]


def register(cli: typer.Typer) -> None:
    """Attach ``trustlab bridge`` to the top-level command."""
    cli.add_typer(bridge, name="bridge")


def _vendor(module: str, kind: str) -> Any:
    """The adapter module of ``kind``; one line when its vendor client is not installed."""
    try:
        return importlib.import_module(f"app.robots.{module}")
    except ModuleNotFoundError as missing:
        if (missing.name or "app").startswith("app"):
            raise
        fail(f"the {kind} bridge needs the vendor client {missing.name!r}: {INSTALL_HINT}")


def _run(robot: Robot, settings: BridgeSettings) -> None:
    """Run the bridge until Ctrl-C (or SIGTERM); refusals are one line and exit 1."""
    import asyncio

    from app.client import ApiError, DeviceKeyRefused
    from app.robots.bridge import Bridge, BridgeRefused

    async def serve() -> None:
        loop = asyncio.get_running_loop()
        runner = Bridge(robot, settings, say=lambda line: typer.echo(line))
        await runner.start()
        for stop in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(stop, runner.stop)
        try:
            await runner.run()
        finally:
            await runner.close()
        typer.echo("Bridge: stopped.")

    try:
        asyncio.run(serve())
    except BridgeRefused as refused:
        fail(str(refused))
    except DeviceKeyRefused as refused:
        fail(f"the server refused the device key: {refused.reason}; ask for a new key")
    except ApiError as refused:
        fail(f"the server refused: {refused.detail}")
    except KeyboardInterrupt:
        print(file=sys.stderr)


def _settings(url: str, station: str, key: str, trigger: Trigger, speaks: str) -> BridgeSettings:
    from app.i18n.languages import UnknownLanguage, check_code
    from app.robots.bridge import BridgeSettings

    try:
        check_code(speaks)
    except UnknownLanguage as exc:
        fail(f"--speaks: {exc}", code=2)
    return BridgeSettings(url=url, station=station, key=key, trigger=trigger, speaks=speaks)


@bridge.command("naoqi")
def naoqi(
    url: Url,
    station: StationName,
    key: Key,
    trigger: TriggerOption = Trigger.PRESENCE,
    speaks: Speaks = "en",
    host: Host = "127.0.0.1",
    port: Annotated[
        int | None,
        typer.Option(
            min=1, max=65535, help="NAOqi's port (default 9559, or 9503 with a password)."
        ),
    ] = None,
    user: Annotated[str, typer.Option(help="NAOqi 2.9's user (with a password).")] = "nao",
    password_stdin: Annotated[
        bool,
        typer.Option(
            "--password-stdin",
            help="Read NAOqi 2.9's password from standard input (connects over tcps).",
        ),
    ] = False,
    language: Language = "English",
    voice: Voice = None,
    volume: Annotated[
        float | None, typer.Option(min=0.0, max=1.0, help="Speech volume, 0-1.")
    ] = None,
    animated: Annotated[
        bool,
        typer.Option(
            help="Play the protocol's gestures with ALAnimatedSpeech (--no-animated: plain "
            "speech, for a robot without it)."
        ),
    ] = True,
    cue_event: Annotated[
        list[str] | None,
        typer.Option(
            help="ALMemory touch event that cues a question (repeatable; default: the three "
            "head sensors)."
        ),
    ] = None,
    led_group: Annotated[
        str,
        typer.Option(
            help="ALLeds group that shows the protocol's reply colours ('' leaves the LEDs alone)."
        ),
    ] = "FaceLeds",
) -> None:
    """A Pepper or NAO, through NAOqi (qi)."""
    adapter = _vendor("naoqi", "NAOqi")
    password = sys.stdin.readline().rstrip("\r\n") or None if password_stdin else None
    options = adapter.NaoqiOptions(
        host=host,
        port=port,
        user=user,
        password=password,
        language=language,
        voice=voice,
        volume=volume,
        animated=animated,
        cue_events=tuple(cue_event) if cue_event else adapter.HEAD_SENSORS,
        led_group=led_group or None,
    )
    _run(adapter.NaoqiRobot(options), _settings(url, station, key, trigger, speaks))


@bridge.command("furhat")
def furhat(
    url: Url,
    station: StationName,
    key: Key,
    trigger: TriggerOption = Trigger.PRESENCE,
    speaks: Speaks = "en",
    host: Host = "localhost",
    port: Annotated[
        int, typer.Option(min=1, max=65535, help="The Remote API skill's port.")
    ] = 54321,
    voice: Voice = None,
    language: Language = "en-US",
) -> None:
    """A Furhat, through its Remote API skill (furhat-remote-api)."""
    adapter = _vendor("furhat", "Furhat")
    options = adapter.FurhatOptions(host=host, port=port, voice=voice, language=language)
    _run(adapter.FurhatRobot(options), _settings(url, station, key, trigger, speaks))


@bridge.command("rosbridge")
def rosbridge(
    url: Url,
    station: StationName,
    key: Key,
    trigger: TriggerOption = Trigger.PRESENCE,
    speaks: Speaks = "en",
    host: Host = "localhost",
    port: Annotated[
        int, typer.Option(min=1, max=65535, help="rosbridge_server's WebSocket port.")
    ] = 9090,
    language: Language = "en-US",
    say_topic: Annotated[
        str, typer.Option(help="std_msgs/String topic the robot speaks from.")
    ] = "/trustlab/say",
    said_topic: Annotated[
        str, typer.Option(help="std_msgs/String topic the robot reports a line said on.")
    ] = "/trustlab/said",
    gesture_topic: Annotated[
        str, typer.Option(help="std_msgs/String topic for gestures ('' sends none).")
    ] = "/trustlab/gesture",
    listen_topic: Annotated[
        str, typer.Option(help="std_msgs/String topic that asks the recogniser to listen.")
    ] = "/trustlab/listen",
    cancel_topic: Annotated[
        str,
        typer.Option(
            help="std_msgs/String topic that cancels a listen the bridge gave up on ('' sends "
            "none)."
        ),
    ] = "/trustlab/listen_cancel",
    heard_topic: Annotated[
        str, typer.Option(help="std_msgs/String topic the recogniser reports on.")
    ] = "/trustlab/heard",
    cue_topic: Annotated[
        str, typer.Option(help="std_msgs/String topic of the robot's cue to ask.")
    ] = "/trustlab/cue",
    led_topic: Annotated[
        str,
        typer.Option(
            help="std_msgs/ColorRGBA topic for the protocol's reply colours ('' sends none)."
        ),
    ] = "/trustlab/led",
) -> None:
    """A ROS 2 robot, through rosbridge_server's WebSocket (roslibpy)."""
    adapter = _vendor("rosbridge", "ROS 2")
    options = adapter.RosbridgeOptions(
        host=host,
        port=port,
        language=language,
        say_topic=say_topic,
        said_topic=said_topic,
        gesture_topic=gesture_topic or None,
        listen_topic=listen_topic,
        cancel_topic=cancel_topic or None,
        heard_topic=heard_topic,
        cue_topic=cue_topic,
        led_topic=led_topic or None,
        require_cue_topic=trigger == Trigger.ROBOT,
    )
    _run(adapter.RosbridgeRobot(options), _settings(url, station, key, trigger, speaks))
