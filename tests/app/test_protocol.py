"""Protocol files: the shipped default, and bad files refused with file, key path and reason."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.protocol import (
    ProtocolError,
    default_protocol,
    load_protocol_file,
    parse_protocol,
    protocol_from_dict,
)
from tests.conftest import protocol_text


def test_default_protocol_is_the_seed_papers() -> None:
    protocol = default_protocol().protocol
    assert [c.id for c in protocol.conditions] == ["C1", "C2"]
    assert [c.learner for c in protocol.conditions] == ["exp3", "meta"]
    assert [c.name for c in protocol.categories] == ["conation", "affection", "cognition"]
    assert all(len(c.questions) == 4 for c in protocol.categories)
    assert protocol.category("cognition").preferred == 1
    assert (protocol.schedule.sessions, protocol.schedule.runs_per_session) == (4, 3)
    assert protocol.schedule.familiarisation_run
    assert protocol.replies.thresholds == [0.5, 0.65, 0.8]
    assert protocol.replies.levels[-1].text == "Awesome, I knew you would say so."
    assert protocol.replies.basis == "heard"  # never a line that contradicts the answer
    assert protocol.allocation.block_sizes == [2, 4]
    keys = {i.key: [item.key for item in i.items] for i in protocol.questionnaires.instruments}
    assert keys["tipi"] == [f"tipi_{n}" for n in range(1, 11)]
    assert keys["nars"] == [f"nars_{n}" for n in range(1, 15)]
    assert keys["trust"] == [f"trust_{n}" for n in range(1, 6)]
    trust = protocol.instruments_at("session")[0]
    assert [item.reverse for item in trust.items] == [False, False, False, False, True]
    reverse_nars = {i.key for i in protocol.instruments_at("pre")[3].items if i.reverse}
    assert reverse_nars == {"nars_3", "nars_5", "nars_6"}


def test_validated_protocol_round_trips_through_json() -> None:
    protocol = default_protocol().protocol
    assert protocol_from_dict(protocol.model_dump(mode="json")) == protocol


def test_protocol_hash_is_of_the_exact_text() -> None:
    loaded = default_protocol()
    changed = parse_protocol(loaded.source_text + "\n# a comment\n")
    assert changed.protocol == loaded.protocol
    assert changed.sha256 != loaded.sha256


def _problems(text: str) -> str:
    with pytest.raises(ProtocolError) as caught:
        parse_protocol(text, source="lab.toml")
    return str(caught.value)


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            '    "Do you come here to stay with me?",\n'
            '    "Did you come here to bring me something?",\n'
            '    "Did you come here to look for your friends?",\n',
            "",
            "lab.toml: categories[0].questions: List should have at least 2 items",
        ),
        (
            "thresholds = [0.5, 0.65, 0.8]",
            "thresholds = [0.5, 0.8, 0.65]",
            "lab.toml: replies.thresholds: thresholds must be strictly increasing",
        ),
        (
            "block_sizes = [2, 4]",
            "block_sizes = [2, 3]",
            "lab.toml: allocation.block_sizes[1]: block size 3 is not a positive multiple",
        ),
        ("sessions = 4", "sessions = 0", "lab.toml: schedule.sessions: Input should be greater"),
        (
            "sessions = 4",
            "sessions = 4\nsesions = 5",
            "lab.toml: schedule.sesions: Extra inputs are not permitted",
        ),
        ("preferred = 1", "preferred = 9", "lab.toml: categories[2].preferred: index 9"),
        (
            'learner = "meta"',
            'learner = "ucb"',
            "lab.toml: conditions[1].learner: Input should be 'exp3', 'meta' or 'bayes'",
        ),
        ('id = "C2"', 'id = "C1"', "lab.toml: conditions[1]: duplicate condition id 'C1'"),
        (
            'text = "I perceive the robot as trustworthy.", scale = "agree5"',
            'text = "I perceive the robot as trustworthy.", scale = "agree7"',
            "lab.toml: questionnaires.instruments[4].items[0].scale: "
            "no response scale named 'agree7'",
        ),
        (
            'items = ["tipi_1", "tipi_6"]',
            'items = ["tipi_1", "tipi_66"]',
            "lab.toml: questionnaires.scores[0].items[1]: 'tipi' has no item 'tipi_66'",
        ),
        ("gamma = 0.5", "gamma = 0.0", "lab.toml: learners.exp3.gamma: Input should be greater"),
        (
            "slip_values = [0.0, 0.025, 0.05, 0.075, 0.1]\n"
            "slip_weights = [0.2, 0.2, 0.2, 0.2, 0.2]",
            "slip = 0.5",
            "lab.toml: learners.feedback.slip: Input should be less than 0.5",
        ),
        (
            "hazard = 0.02",
            "hazard = -0.1",
            "lab.toml: learners.feedback.hazard: Input should be greater than or equal to 0",
        ),
        (
            "slip_weights = [0.2, 0.2, 0.2, 0.2, 0.2]",
            "slip_weights = [0.2, 0.2, 0.2, 0.2, 0.3]",
            "lab.toml: learners.feedback.slip_weights: must be non-negative and sum to 1",
        ),
        (
            "slip_values = [0.0, 0.025, 0.05, 0.075, 0.1]",
            "slip_values = [0.0, 0.025, 0.05, 0.075, 0.6]",
            "lab.toml: learners.feedback.slip_values: every slip rate must lie in [0, 0.5)",
        ),
        (
            "slip_weights = [0.2, 0.2, 0.2, 0.2, 0.2]",
            "",
            "lab.toml: learners.feedback: give slip_values and slip_weights together",
        ),
        (
            "hazard = 0.02",
            "hazard = 0.02\nslip = 0.05",
            "lab.toml: learners.feedback.slip: give either slip or a slip prior, not both",
        ),
        (
            'basis = "heard"',
            'basis = "confident"',
            "lab.toml: replies.basis: Input should be 'chosen', 'updated' or 'heard'",
        ),
        (
            '    { name = "high", text = "Awesome, I knew you would say so." },\n',
            "",
            "lab.toml: replies.levels: 3 thresholds need 4 levels, found 3",
        ),
        (
            '{ name = "high", text = "Awesome, I knew you would say so." }',
            '{ name = "high", yes = "Awesome, I knew you would say so." }',
            "lab.toml: replies.levels[3].no: level 'high' has no line for a 'no' answer: give "
            "`no`, or `text` for both answers",
        ),
        (
            '{ name = "low", text = "I do not believe it but fine." }',
            '{ name = "low", text = "Fine.", yes = "Really?", no = "Really not?" }',
            "lab.toml: replies.levels[0].text: never said: `yes` and `no` give both answers' lines",
        ),
    ],
)
def test_bad_protocol_names_file_key_path_and_reason(old: str, new: str, expected: str) -> None:
    assert expected in _problems(protocol_text(**{old: new}))


def test_every_problem_is_listed_one_per_line() -> None:
    text = protocol_text(
        **{"sessions = 4": "sessions = 0", "block_sizes = [2, 4]": "block_sizes = []"}
    )
    lines = _problems(text).splitlines()
    assert len(lines) == 2
    assert all(line.startswith("lab.toml: ") for line in lines)


def test_both_kinds_of_mistake_are_reported_at_once_in_file_order() -> None:
    """Issue 35 item 9: a misspelt key (per-field) no longer hides a bad block size (cross-field);
    the guide's example, line for line."""
    text = protocol_text(
        **{"block_sizes = [2, 4]": "block_sizes = [2, 3]", "sessions = 4": "sesions = 4"}
    )
    assert _problems(text).splitlines() == [
        "lab.toml: schedule.sesions: Extra inputs are not permitted",
        "lab.toml: allocation.block_sizes[1]: block size 3 is not a positive multiple of the 2 "
        "conditions",
    ]


def test_every_mistake_of_a_file_is_listed() -> None:
    text = protocol_text(
        **{
            "gamma = 0.5": "gamma = 0.0",
            "preferred = 1": "preferred = 9",
            "sessions = 4": "sessions = 0",
            "block_sizes = [2, 4]": "block_sizes = [2, 3]",
            'id = "C2"': 'id = "C1"\ncolour = "red"',
        }
    )
    assert _problems(text).splitlines() == [
        "lab.toml: conditions[1]: duplicate condition id 'C1'",
        "lab.toml: conditions[1].colour: Extra inputs are not permitted",
        "lab.toml: learners.exp3.gamma: Input should be greater than 0",
        "lab.toml: categories[2].preferred: index 9 but only 4 questions",
        "lab.toml: schedule.sessions: Input should be greater than or equal to 1",
        "lab.toml: allocation.block_sizes[1]: block size 3 is not a positive multiple of the 2 "
        "conditions",
    ]


def test_every_reply_table_problem_is_listed_with_the_others() -> None:
    text = protocol_text(
        **{
            '{ name = "low", text = "I do not believe it but fine." }': '{ name = "low" }',
            '{ name = "high", text = "Awesome, I knew you would say so." }': (
                '{ name = "high", no = "I thought you would say no." }'
            ),
            "sessions = 4": "sessions = 0",
        }
    )
    assert _problems(text).splitlines() == [
        "lab.toml: schedule.sessions: Input should be greater than or equal to 1",
        "lab.toml: replies.levels[0].yes: level 'low' has no line for a 'yes' answer: give "
        "`yes`, or `text` for both answers",
        "lab.toml: replies.levels[0].no: level 'low' has no line for a 'no' answer: give "
        "`no`, or `text` for both answers",
        "lab.toml: replies.levels[3].yes: level 'high' has no line for a 'yes' answer: give "
        "`yes`, or `text` for both answers",
    ]


def test_a_reply_level_can_give_a_line_per_answer() -> None:
    text = protocol_text(
        **{
            '{ name = "high", text = "Awesome, I knew you would say so." }': (
                '{ name = "high", yes = "Awesome, I knew you would say so.", '
                'no = "I thought you would say no." }'
            ),
            '{ name = "low", text = "I do not believe it but fine." }': (
                '{ name = "low", text = "I do not believe it but fine.", no = "Really? Fine." }'
            ),
        }
    )
    levels = parse_protocol(text).protocol.replies.levels
    assert [levels[3].line(True), levels[3].line(False)] == [
        "Awesome, I knew you would say so.",
        "I thought you would say no.",
    ]
    assert [levels[0].line(True), levels[0].line(False)] == [
        "I do not believe it but fine.",
        "Really? Fine.",
    ]


_LEVELS = '\nlevels = [\n    { name = "low", text = "I do not believe it but fine." },\n'


@pytest.mark.parametrize(
    ("replacements", "expected"),
    [
        # Unreadable thresholds: their number cannot be checked against the (now 3) levels.
        (
            {f"thresholds = [0.5, 0.65, 0.8]{_LEVELS}": 'thresholds = "0.5"\nlevels = [\n'},
            "lab.toml: replies.thresholds: Input should be a valid list",
        ),
        # A third condition without a learner: the stand-in's two conditions say nothing of
        # blocks of 3, which suit the file's three.
        (
            {
                'neutral_label = "Group B"\n': 'neutral_label = "Group B"\n\n'
                '[[conditions]]\nid = "C3"\nlabel = "Third"\n',
                "block_sizes = [2, 4]": "block_sizes = [3, 6]",
            },
            "lab.toml: conditions[2].learner: Field required",
        ),
    ],
)
def test_no_problem_is_reported_about_a_value_the_file_does_not_hold(
    replacements: dict[str, str], expected: str
) -> None:
    assert _problems(protocol_text(**replacements)).splitlines() == [expected]


def test_invalid_toml_reports_the_position() -> None:
    message = _problems("[study]\ntitle = \n")
    assert message.startswith("lab.toml: not valid TOML: ")
    assert "line 2" in message


def test_unreadable_file_is_a_protocol_error(tmp_path: Path) -> None:
    with pytest.raises(ProtocolError, match="cannot read the file"):
        load_protocol_file(tmp_path / "missing.toml")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ProtocolError, match=str(binary)):
        load_protocol_file(binary)
