"""StudyDataset validation and the protocol summary."""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import pandas as pd
import pytest

from analysis.dataset import StudyDataset, empty_steps, validate_protocol
from analysis.errors import InvalidInputError
from analysis.synthetic import SEED_PAPER_PROTOCOL, synthetic_study


@pytest.fixture(scope="module")
def small() -> StudyDataset:
    return synthetic_study(6, seed=3)


def test_synthetic_study_shape(small: StudyDataset) -> None:
    assert list(small.participants.columns[:3]) == ["participant", "condition", "status"]
    assert small.attribute_columns == ["gender_stratum"]
    assert set(small.participants["condition"]) == {"C1", "C2"}
    # 2 demographics + 3 background + 10 TIPI + 14 NARS + 5 trust × 4 sessions per person
    assert len(small.responses) == 6 * (2 + 3 + 10 + 14 + 20)
    assert len(small.steps) == 6 * 3 * 12
    assert small.condition_labels == {"C1": "Exp3", "C2": "meta-learned policy"}
    assert small.instrument("trust").per_session
    with pytest.raises(InvalidInputError, match="no instrument 'bfi'"):
        small.instrument("bfi")


def test_synthetic_is_reproducible() -> None:
    a, b = synthetic_study(4, seed=9), synthetic_study(4, seed=9)
    pd.testing.assert_frame_equal(a.responses, b.responses)
    assert not synthetic_study(4, seed=10).responses.equals(a.responses)


def test_steps_default_to_empty() -> None:
    ds = synthetic_study(4, seed=1, with_steps=False)
    assert ds.steps.empty
    assert list(ds.steps.columns) == list(empty_steps().columns)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: {"participants": d.participants.drop(columns="status")}, "no column 'status'"),
        (
            lambda d: {"participants": pd.concat([d.participants, d.participants.iloc[[0]]])},
            "appear twice",
        ),
        (
            lambda d: {"responses": d.responses.assign(participant="P99999")},
            "not in participants",
        ),
        (lambda d: {"steps": d.steps.assign(participant="ghost")}, "not in participants"),
        (
            lambda d: {"participants": d.participants.assign(condition="C3")},
            "not in the protocol",
        ),
        (lambda d: {"responses": d.responses.drop(columns="item")}, "no column 'item'"),
        (lambda d: {"responses": "not a frame"}, "must be a pandas DataFrame"),
    ],
)
def test_dataset_refuses_inconsistent_frames(small: StudyDataset, change, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInputError, match=message):
        dataclasses.replace(small, **change(small))


def _protocol(**changes: Any) -> dict[str, Any]:
    protocol: dict[str, Any] = copy.deepcopy(dict(SEED_PAPER_PROTOCOL))
    protocol.update(changes)
    return protocol


@pytest.mark.parametrize(
    ("protocol", "message"),
    [
        (
            {k: v for k, v in SEED_PAPER_PROTOCOL.items() if k != "sessions"},
            "missing key 'sessions'",
        ),
        (_protocol(sessions="4"), r"protocol\.sessions: expected int"),
        (_protocol(sessions=0), "at least 1"),
        (_protocol(conditions=[{"code": "C1"}]), r"conditions\[0\]"),
        (_protocol(preferred_arms={"conation": 9, "affection": 0, "cognition": 1}), "not an arm"),
        (_protocol(preferred_arms={"conation": 0, "affection": 0}), "no preferred arm"),
        (
            _protocol(preferred_arms={"x": 0, "conation": 0, "affection": 0, "cognition": 1}),
            "unknown",
        ),
        ([], "must be a dict"),
    ],
)  # fmt: skip
def test_protocol_is_validated_with_key_path(protocol: Any, message: str) -> None:
    with pytest.raises(InvalidInputError, match=message):
        validate_protocol(protocol)


def test_seed_paper_protocol_is_valid() -> None:
    validate_protocol(SEED_PAPER_PROTOCOL)
    assert SEED_PAPER_PROTOCOL["preferred_arms"]["cognition"] == 1  # "you need the second key"
