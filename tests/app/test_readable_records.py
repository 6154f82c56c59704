"""Records staff read at a glance (issue 21, defect 9): audit details as key/value pairs, and
participant timelines with each item's text and the words for the answer chosen."""

from __future__ import annotations

from app.protocol import default_protocol
from app.services.participants.timeline import _meaning
from app.tables import Role
from app.web.audit_pages import detail_pairs
from tests.conftest import Lab, UserClientFactory


def test_audit_details_read_as_labelled_values() -> None:
    assert detail_pairs(
        {"block_size": 4, "replaces_participant_id": None, "blinded": True, "stratum": {}}
    ) == [
        ("block size", "4"),
        ("replaces participant id", "—"),
        ("blinded", "yes"),
        ("stratum", "none"),
    ]
    assert detail_pairs({"categories": ["conation", "affection"], "stratum": {"gender": "f"}}) == [
        ("categories", "conation, affection"),
        ("stratum", "gender f"),
    ]
    assert detail_pairs({"reason": ""}) == [("reason", "—")]
    assert detail_pairs(None) == [] and detail_pairs({}) == []


def test_answers_are_given_their_scale_points_words() -> None:
    protocol = default_protocol().protocol
    items = {item.key: item for i in protocol.questionnaires.instruments for item in i.items}
    assert _meaning(protocol, items["trust_1"], "4") == "Agree"  # every point labelled
    anchors = next(i for i in items.values() if i.scale == "amount5")
    assert _meaning(protocol, anchors, "1") == "Very little"  # two anchors: the ends only
    assert _meaning(protocol, anchors, "3") == ""
    assert _meaning(protocol, items["gender"], "female") == "Female"
    assert _meaning(protocol, items["age"], "27") == ""
    assert _meaning(protocol, items["trust_1"], "not a number") == ""


def test_a_timeline_shows_item_texts_beside_their_keys(
    lab: Lab, user_client: UserClientFactory
) -> None:
    code = lab.enrol_and_assign()
    page = user_client(Role.ANALYST).get(f"/studies/{lab.study}/participants/{code}").text
    assert "<code>age</code></th><td>How old are you (in years)?</td>" in page
    assert 'female <span class="muted small">(Female)</span>' in page
    assert "reverse-scored</span>" in page  # the TIPI's reverse-keyed items are marked
