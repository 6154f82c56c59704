"""``trustlab bridge`` as a lab runs it: refusals are one line with a non-zero exit and send
nothing, and a bridge process killed mid-question and started again records the answer once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from sqlalchemy import func, select
from typer.testing import CliRunner

from app.cli import cli
from app.services.sessions import verify
from app.tables import Answer, Prompt
from tests.conftest import Lab
from tests.robots.harness import BOUND, console_badge, wait_for
from tests.robots.standins.furhat import FurhatStandIn
from tests.robots.standins.rosbridge import RosbridgeStandIn
from tests.robots.standins.script import Script
from tests.servers import free_port

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True),
]


def _count(lab: Lab, table: type[Answer] | type[Prompt]) -> int:
    with lab.database.read_session() as db:
        return int(db.scalar(select(func.count()).select_from(table)) or 0)


def test_refusals_are_one_line_exit_1_and_send_nothing(lab: Lab, url: str) -> None:
    lab.enrol_and_assign("P001")
    lab.start_session()
    runner = CliRunner()
    with FurhatStandIn(Script()) as robot:
        furhat = ["--host", robot.host, "--port", str(robot.port)]
        cases = {
            "the key belongs to station 'lab-1', not 'lab-9'": [
                "furhat",
                "--url",
                url,
                "--station",
                "lab-9",
                "--key",
                lab.key,
                *furhat,
            ],
            "refused the key": [
                "furhat",
                "--url",
                url,
                "--station",
                "lab-1",
                "--key",
                "tlk_wrong",
                *furhat,
            ],
            f"cannot reach the trustlab server at http://127.0.0.1:{free_port()}": [],
            "connection refused; is the robot on and its Remote API skill running?": [
                "furhat",
                "--url",
                url,
                "--station",
                "lab-1",
                "--key",
                lab.key,
                "--port",
                str(free_port()),
            ],
            "Missing option '--station'": ["furhat", "--url", url, "--key", lab.key],
        }
        for reason, arguments in cases.items():
            if not arguments:  # the server's address is in the reason
                address = reason.rsplit(" ", 1)[1]
                arguments = ["furhat", "--url", address, "--station", "lab-1", "--key", lab.key]
                arguments += furhat
            result = runner.invoke(cli, ["bridge", *arguments])
            assert result.exit_code != 0, (reason, result.output)
            assert reason in result.output, (reason, result.output)
            if "Missing option" not in reason:
                assert result.exit_code == 1
                assert result.output.count("error:") == 1 and "Traceback" not in result.output
        assert robot.script.said == []
    with RosbridgeStandIn(Script(), missing_topics=["/trustlab/heard"]) as ros:
        arguments = ["bridge", "rosbridge", "--url", url, "--station", "lab-1", "--key", lab.key]
        result = runner.invoke(cli, [*arguments, "--host", "127.0.0.1", "--port", str(ros.port)])
    assert result.exit_code == 1, result.output
    assert result.output.startswith("error: rosbridge at ws://127.0.0.1:") and "\n" not in (
        result.output.strip()
    )
    assert "no topic /trustlab/heard (where the robot's recogniser reports)" in result.output
    nobody = free_port()
    arguments = ["bridge", "naoqi", "--url", url, "--station", "lab-1", "--key", lab.key]
    result = runner.invoke(cli, [*arguments, "--port", str(nobody)])
    assert result.exit_code == 1, result.output
    assert result.output.startswith(f"error: cannot reach NAOqi at tcp://127.0.0.1:{nobody}")
    assert (_count(lab, Prompt), _count(lab, Answer)) == (0, 0)


def _bridge_process(url: str, lab: Lab, robot: FurhatStandIn, log: Path) -> subprocess.Popen[bytes]:
    command = [sys.executable, "-c", "from app.cli import main; main()", "bridge", "furhat"]
    command += ["--url", url, "--station", lab.station, "--host", robot.host]
    command += ["--port", str(robot.port), "--trigger", "console"]
    environment = {**os.environ, "TRUSTLAB_DEVICE_KEY": lab.key}
    with log.open("ab") as output:
        return subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT, env=environment)


def _wait_for(condition: object, what: str, process: subprocess.Popen[bytes], log: Path) -> None:
    """Wait (bounded) until ``condition()`` holds; fail with the bridge's output otherwise."""
    for _ in range(int(BOUND / 0.05)):
        if condition():  # type: ignore[operator]
            return
        if process.poll() is not None:
            break
        threading.Event().wait(0.05)
    raise AssertionError(f"never {what}; the bridge printed:\n{log.read_text()}")


def test_a_bridge_killed_mid_question_answers_once_after_restart(
    lab: Lab, url: str, tmp_path: Path
) -> None:
    lab.enrol_and_assign("P001")
    lab.start_session()
    log = tmp_path / "bridge.log"
    script = Script()
    with FurhatStandIn(script, listen_until_stopped=True) as robot:
        first = _bridge_process(url, lab, robot, log)
        try:
            _wait_for(lambda: "joined station lab-1" in log.read_text(), "joined", first, log)
            assert console_badge(lab) == "connected"
            step = lab.experimenter.post(
                f"/api/v1/stations/{lab.station}/prompts", json={"category": "conation"}
            ).json()
            _wait_for(lambda: robot.queries("/furhat/listen"), "listened", first, log)
            first.send_signal(signal.SIGKILL)  # while the robot listens
            first.wait(BOUND)
        finally:
            first.kill()
        wait_for(lambda: console_badge(lab) == "not connected")  # its socket died with it
        assert _count(lab, Answer) == 0
        robot.listen_until_stopped = False
        script.add("yes")
        second = _bridge_process(url, lab, robot, log)
        try:
            said = script.wait_said(3, BOUND)
            assert console_badge(lab) == "connected"
            second.send_signal(signal.SIGINT)
            assert second.wait(BOUND) == 0
        finally:
            second.kill()
    [answer] = lab.database.read_session().scalars(select(Answer)).all()
    assert (answer.prompt_id, answer.answer, answer.transcript) == (step["step_id"], True, "yes")
    assert [line.text for line in said] == [step["question"], step["question"], answer.reply]
    assert "Bridge: stopped." in log.read_text()
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.findings
