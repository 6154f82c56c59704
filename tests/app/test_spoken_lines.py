"""Speech from the server for rooms whose browser has no voices: the study's lines only."""

from __future__ import annotations

import io
import logging
import shutil
import wave

import pytest

from app.protocol import default_protocol
from app.speech.lines import ROOM_LINES, spoken_lines
from app.speech.synthesis import Synthesiser
from tests.conftest import Lab

SPOKEN = "/api/v1/station/speech/audio"


def test_the_lines_are_the_studys_questions_replies_reprompt_and_rules() -> None:
    protocol = default_protocol().protocol
    lines = spoken_lines(protocol)
    assert set(protocol.categories[0].questions) <= lines
    assert protocol.replies.levels[0].text in lines
    assert protocol.speech.reprompt in lines
    assert set(protocol.study.rules) <= lines
    assert set(ROOM_LINES) <= lines
    assert "Open the pod bay doors." not in lines


@pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng is not installed")
def test_a_line_of_the_study_is_spoken_and_any_other_text_refused(lab: Lab) -> None:
    lab.enrol_and_assign()
    question = default_protocol().protocol.categories[0].questions[0]
    spoken = lab.robot.get(SPOKEN, params={"text": question})
    assert spoken.status_code == 200, spoken.text
    assert spoken.headers["content-type"] == "audio/wav"
    with wave.open(io.BytesIO(spoken.content)) as wav:
        assert wav.getnframes() > wav.getframerate() // 2  # at least half a second of speech
        assert len(spoken.content) == 44 + wav.getnframes() * wav.getsampwidth()
    again = lab.robot.get(SPOKEN, params={"text": question})
    assert again.content == spoken.content
    refused = lab.robot.get(SPOKEN, params={"text": "Open the pod bay doors."})
    assert refused.status_code == 404
    assert "not a line of study 'rt'" in refused.json()["detail"]
    assert lab.robot.get(SPOKEN).status_code == 422
    anonymous = lab.experimenter.get(SPOKEN, params={"text": question})
    assert anonymous.status_code == 401


def test_without_espeak_ng_the_room_gets_a_503_and_the_log_one_line(
    lab: Lab, caplog: pytest.LogCaptureFixture
) -> None:
    missing = Synthesiser()
    missing.program = None  # as on a server without the package
    lab.app.state.synthesiser = missing
    lab.enrol_and_assign()
    question = default_protocol().protocol.categories[0].questions[0]
    with caplog.at_level(logging.WARNING, logger="app.speech.synthesis"):
        for _ in range(2):
            refused = lab.robot.get(SPOKEN, params={"text": question})
            assert refused.status_code == 503
            assert "espeak-ng is not installed" in refused.json()["detail"]
            assert "\n" not in refused.json()["detail"]
    said = [r for r in caplog.records if r.name == "app.speech.synthesis"]
    assert len(said) == 1 and "\n" not in said[0].getMessage()
