"""Export tables, codebook, SPSS file and the format registry."""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyreadstat
import pytest

from analysis.dataset import StudyDataset
from analysis.errors import InvalidInputError
from analysis.exports import (
    ADAPTATION_BASE_COLUMNS,
    CODEBOOK_COLUMNS,
    EXPORT_FORMATS,
    LONG_COLUMNS,
    adaptation_trust_table,
    codebook_json,
    codebook_table,
    csv_bytes,
    long_table,
    sha256_file,
    spss_name,
    steps_table,
    wide_table,
    write_all_exports,
    write_export,
    write_sav,
)
from analysis.instruments import DEFAULT_INSTRUMENTS, InstrumentSpec, ItemSpec
from analysis.synthetic import synthetic_study


def dataset_with(dataset: StudyDataset, **frames: pd.DataFrame) -> StudyDataset:
    return dataclasses.replace(dataset, **frames)


@pytest.fixture(scope="module")
def dataset() -> StudyDataset:
    ds = synthetic_study(6, seed=4, dropout_rate=0.3)
    people = ds.participants.assign(**{"site name": ["A", "B", "A", "B", "A", "B"]})
    return dataclasses.replace(ds, participants=people)


def test_long_table_raw_and_scored(dataset: StudyDataset) -> None:
    out = long_table(dataset)
    assert tuple(out.columns) == LONG_COLUMNS
    assert len(out) == len(dataset.responses)
    trust5 = out[out["item"] == "trust_5"]
    np.testing.assert_allclose(trust5["scored"], 6 - trust5["value"].astype(float))
    tipi2 = out[out["item"] == "tipi_2"]
    np.testing.assert_allclose(tipi2["scored"], 8 - tipi2["value"].astype(float))
    first = out[out["participant"] == "P00001"]
    assert first["instrument"].iloc[0] == "demographics"  # questionnaire order
    assert (
        list(first[first["item"] == "trust_1"]["session"])
        == [1, 2, 3, 4][: len(first[first["item"] == "trust_1"])]
    )
    assert out["condition"].notna().all()


def test_wide_table_names_and_values(dataset: StudyDataset) -> None:
    wide = wide_table(dataset)
    assert len(wide) == 6
    assert wide.columns[:5].tolist() == [
        "participant",
        "condition",
        "status",
        "gender_stratum",
        "site_name",
    ]
    for column in ("trust_1_s1", "trust_5_s4", "trust_5_r_s4", "tipi_2_r", "nars_s1_sum", "age"):
        assert column in wide.columns
    assert all(spss_name(c) == c for c in wide.columns)  # valid SPSS/JASP names
    responses = dataset.responses
    row = wide.set_index("participant").loc["P00002"]
    raw = responses[(responses.participant == "P00002") & (responses["item"] == "trust_5")]
    for session, value in zip(raw["session"], raw["value"], strict=True):
        assert row[f"trust_5_s{session}"] == value
        assert row[f"trust_5_r_s{session}"] == 6 - value
    tipi = responses[(responses.participant == "P00002") & (responses.instrument == "tipi")]
    answers = dict(zip(tipi["item"], tipi["value"], strict=True))
    assert row["tipi_extraversion"] == (answers["tipi_1"] + 8 - answers["tipi_6"]) / 2


def test_an_attribute_named_like_an_item_keeps_both_columns(dataset: StudyDataset) -> None:
    """A stratification factor ``age`` beside the demographics item ``age``: neither is lost (the
    attribute's column is renamed, as the codebook says)."""
    people = dataset.participants.assign(age=["young", "old"] * 3)
    wide = wide_table(dataset_with(dataset, participants=people))
    assert list(wide["age_2"]) == ["young", "old"] * 3
    answered = dataset.responses[dataset.responses["item"] == "age"]
    ages = dict(zip(answered["participant"], answered["value"], strict=True))
    row = wide.set_index("participant").loc["P00002"]
    assert row["age"] == ages["P00002"]
    codebook = codebook_table(dataset_with(dataset, participants=people))
    wide_rows = codebook[codebook["file"] == "wide"]
    assert {"age", "age_2"} <= set(wide_rows["column"])


def test_wide_table_keeps_columns_for_missing_sessions(dataset: StudyDataset) -> None:
    wide = wide_table(dataset)
    dropped = dataset.participants.loc[dataset.participants.status != "completed", "participant"]
    assert len(dropped)
    assert wide.set_index("participant").loc[dropped, "trust_1_s4"].isna().all()


def test_every_table_of_a_study_with_no_answers_yet(dataset: StudyDataset, tmp_path: Path) -> None:
    """Participants enrolled, nobody has answered yet (the first day of a study): every export
    is written, with a row per participant and every declared column empty (a 500 before)."""
    empty = dataclasses.replace(dataset, responses=dataset.responses.iloc[:0])
    wide = wide_table(empty)
    assert list(wide["participant"]) == list(dataset.participants["participant"])
    assert list(wide.columns) == list(wide_table(dataset).columns)
    assert wide["trust_1_s1"].isna().all()
    assert long_table(empty).empty
    written = write_all_exports(empty, tmp_path / "bundle")
    assert set(written) == set(EXPORT_FORMATS) and all(p.stat().st_size for p in written.values())


def test_codes_arriving_as_text_and_free_text() -> None:
    post = InstrumentSpec(
        "post",
        "Post-study",
        (
            ItemSpec("post_quality", "Quality of interaction", "likert", 1, 5),
            ItemSpec("post_comment", "Anything else?", "text"),
        ),
    )
    ds = synthetic_study(4, seed=1, with_steps=False)
    extra = pd.DataFrame(
        {
            "participant": ["P00001", "P00001", "P00002"],
            "instrument": "post",
            "session": pd.array([pd.NA] * 3, dtype="Int64"),
            "item": ["post_quality", "post_comment", "post_comment"],
            "value": [4, "3", "12"],
        }
    )
    responses = pd.concat([ds.responses.astype({"value": object}), extra], ignore_index=True)
    gender = (responses["item"] == "gender") & (responses.participant == "P00001")
    responses.loc[gender, "value"] = "2"
    wide = wide_table(
        dataclasses.replace(ds, responses=responses, instruments=(*DEFAULT_INSTRUMENTS, post))
    ).set_index("participant")
    assert wide["gender"].dtype == float  # numeric codes, even when one arrived as text
    assert wide.loc["P00001", "gender"] == 2.0
    assert wide.loc["P00001", "post_quality"] == 4.0
    assert wide.loc["P00001", "post_comment"] == "3"  # free text stays text, even digits
    assert wide.loc["P00002", "post_comment"] == "12"
    assert pd.isna(wide.loc["P00003", "post_comment"])


def test_steps_table(dataset: StudyDataset) -> None:
    out = steps_table(dataset)
    assert len(out) == len(dataset.steps)
    assert {"p_before_0", "p_after_3", "preferred_arm", "p_preferred_after"} <= set(out.columns)
    cognition = out[out["category"] == "cognition"]
    assert set(cognition["preferred_arm"]) == {1}
    np.testing.assert_allclose(cognition["p_preferred_after"], cognition["p_after_1"])
    np.testing.assert_allclose(out[[f"p_after_{j}" for j in range(4)]].sum(axis=1), 1.0)
    assert set(out["answer"]) <= {0, 1}
    assert out["category"].iloc[0] == "conation"  # protocol order


def test_steps_say_how_each_answer_was_given_when_the_log_has_it(dataset: StudyDataset) -> None:
    """trustlab's step log carries the modality and, for spoken answers, the transcript, its
    confidence and the recogniser; the steps table and its codebook follow, a log without them
    (another lab's CSV) keeps its columns."""
    n = len(dataset.steps)
    spoken = dataset.steps.assign(
        modality=["speech", "key"] * (n // 2) + ["speech"] * (n % 2),
        transcript=["yeah", None] * (n // 2) + ["yeah"] * (n % 2),
        transcript_confidence=[0.83, None] * (n // 2) + [0.83] * (n % 2),
        transcript_engine=["pocketsphinx 5.1.1 (en-us)", None] * (n // 2)
        + ["pocketsphinx 5.1.1 (en-us)"] * (n % 2),
    )
    out = steps_table(dataset_with(dataset, steps=spoken))
    columns = ["modality", "transcript", "transcript_confidence", "transcript_engine"]
    assert out.columns[out.columns.get_loc("p_preferred_after") + 1 :][:4].tolist() == columns
    assert set(out["modality"]) == {"speech", "key"}
    assert set(out.loc[out.modality == "speech", "transcript"]) == {"yeah"}
    book = codebook_table(dataset_with(dataset, steps=spoken))
    assert set(columns) <= set(book[book.file == "steps"]["column"])
    assert not set(columns) & set(steps_table(dataset).columns)


def test_codebook_covers_every_column(dataset: StudyDataset) -> None:
    book = codebook_table(dataset)
    assert tuple(book.columns) == CODEBOOK_COLUMNS
    wide = wide_table(dataset)
    assert book[book.file == "wide"]["column"].tolist() == wide.columns.tolist()
    assert book[book.file == "long"]["column"].tolist() == list(LONG_COLUMNS)
    assert set(book[book.file == "steps"]["column"]) == set(steps_table(dataset).columns)
    row = book[(book.file == "wide") & (book.column == "trust_5_s2")].iloc[0]
    assert row["label"] == "The robot questioned my answers. [session 2]"
    assert row["reverse_keyed"] == "yes: scored 6 − x"
    assert row["allowed"] == "1–5"
    assert row["value_labels"].startswith("1=Strongly disagree; 2=Disagree")
    assert row["session"] == 2
    assert "Gao" in row["citation"]
    tipi = book[(book.file == "wide") & (book.column == "tipi_1")].iloc[0]
    assert tipi["label"] == "I see myself as: Extraverted, enthusiastic."
    score = book[(book.file == "wide") & (book.column == "nars_s3_sum")].iloc[0]
    assert "nars_3 (reversed)" in score["derivation"]
    assert score["allowed"] == "3–15"
    reversed_column = book[(book.file == "wide") & (book.column == "tipi_2_r")].iloc[0]
    assert reversed_column["derivation"] == "1 + 7 − tipi_2"
    assert reversed_column["value_labels"] == ""


def test_the_codebook_lists_recorded_voices_only_where_they_were_recorded(
    dataset: StudyDataset,
) -> None:
    assert "recordings" not in set(codebook_table(dataset).file)
    recorded = dataclasses.replace(dataset, protocol={**dataset.protocol, "record_audio": True})
    (row,) = codebook_table(recorded).query("file == 'recordings'").to_dict("records")
    assert row["column"] == "wav" and "16 kHz" in row["label"]
    assert "answer_audio" in row["derivation"]
    assert set(codebook_json(recorded)["files"]) == {"wide", "long", "steps", "recordings"}


def test_codebook_json(dataset: StudyDataset) -> None:
    data = codebook_json(dataset)
    json.dumps(data, allow_nan=False)
    assert set(data["files"]) == {"wide", "long", "steps"}
    nars = next(i for i in data["instruments"] if i["name"] == "nars")
    assert [it["key"] for it in nars["items"] if it["reverse"]] == ["nars_3", "nars_5", "nars_6"]
    assert nars["items"][0]["value_labels"]["1"] == "Strongly disagree"
    entry = next(c for c in data["files"]["wide"] if c["column"] == "trust_1_s3")
    assert entry["session"] == 3


def test_sav_round_trip(dataset: StudyDataset, tmp_path: Path) -> None:
    path = write_sav(dataset, tmp_path / "study.sav")
    frame, meta = pyreadstat.read_sav(str(path))
    wide = wide_table(dataset)
    assert frame.columns.tolist() == wide.columns.tolist()
    np.testing.assert_allclose(frame["trust_1_s1"], wide["trust_1_s1"], equal_nan=True)
    assert frame["participant"].tolist() == wide["participant"].tolist()
    assert (
        meta.column_names_to_labels["trust_2_s1"]
        == "The robot perceives me as trustworthy. [session 1]"
    )
    assert meta.variable_value_labels["nars_1"][5.0] == "Strongly agree"
    assert meta.variable_value_labels["gender"][4.0] == "Prefer not to say"
    assert "trust_5_r_s1" not in meta.variable_value_labels
    assert meta.variable_measure["trust_1_s1"] == "ordinal"
    assert meta.variable_measure["age"] == "scale"
    assert meta.variable_measure["condition"] == "nominal"


def test_csv_bytes_are_stable(dataset: StudyDataset) -> None:
    data = csv_bytes(wide_table(dataset))
    assert data == csv_bytes(wide_table(dataset))
    back = pd.read_csv(io.BytesIO(data))
    assert back.shape == wide_table(dataset).shape
    assert b"\r\n" not in data


def test_registry_and_bundle(dataset: StudyDataset, tmp_path: Path) -> None:
    assert set(EXPORT_FORMATS) == {
        "long-csv", "wide-csv", "steps-csv", "codebook-csv", "codebook-json", "sav",
        "adaptation-csv", "mixed-json", "html",
    }  # fmt: skip
    written = write_all_exports(dataset, tmp_path / "bundle")
    mixed = json.loads(written["mixed-json"].read_text(encoding="utf-8"))
    assert mixed["manifest"] == json.loads(json.dumps(dict(dataset.manifest)))
    keys = [o["key"] for o in mixed["outcomes"]]
    assert keys == [f"trust_{i}" for i in range(1, 6)]
    first = mixed["outcomes"][0]
    assert first["lmm"]["models"][0]["df_method"] == "Satterthwaite"
    assert first["ordinal"]["converged"] is True
    assert "Mixed models" in written["html"].read_text(encoding="utf-8")
    assert {p.name for p in written.values()} == {f.filename for f in EXPORT_FORMATS.values()}
    sums = (tmp_path / "bundle" / "SHA256SUMS").read_text().splitlines()
    assert len(sums) == len(EXPORT_FORMATS)
    digest, name = sums[0].split("  ")
    assert sha256_file(tmp_path / "bundle" / name) == digest
    one = write_export(dataset, "long-csv", tmp_path / "long.csv")
    assert pd.read_csv(one).columns.tolist() == list(LONG_COLUMNS)
    with pytest.raises(InvalidInputError, match="unknown export format 'xlsx'"):
        write_export(dataset, "xlsx", tmp_path / "x.xlsx")


@pytest.mark.parametrize(
    ("name", "expected"),
    [("site name", "site_name"), ("2nd", "v_2nd"), ("BY", "BY_"), ("ok_1", "ok_1"), ("ä", "var")],
)
def test_spss_name(name: str, expected: str) -> None:
    assert spss_name(name) == expected
    assert spss_name("x" * 80).__len__() == 64
    assert spss_name("condition", {"Condition"}) == "condition_2"


def test_long_table_order(dataset: StudyDataset) -> None:
    out = long_table(dataset)
    first = out[out["participant"] == dataset.participants["participant"].iloc[0]]
    once = first[first["session"].isna()]
    assert list(once["instrument"].unique()) == ["demographics", "background", "tipi", "nars"]
    assert once["item"].iloc[:2].tolist() == ["age", "gender"]
    trust = first[first["session"].notna()]
    assert trust["session"].is_monotonic_increasing
    assert trust["item"].iloc[:5].tolist() == [f"trust_{i}" for i in range(1, 6)]
    assert first.index.max() < out[out["participant"] != first["participant"].iloc[0]].index.min()


def test_adaptation_table_joins_the_measures_to_the_ratings(dataset: StudyDataset) -> None:
    protocol = {**dataset.protocol, "reply_levels": ["low", "high"]}
    steps = dataset.steps.assign(
        reply_level=[
            int(p[a] >= 0.5)
            for p, a in zip(dataset.steps["probs_before"], dataset.steps["action"], strict=True)
        ]
    )
    with_levels = dataclasses.replace(dataset, steps=steps, protocol=protocol)
    table = adaptation_trust_table(with_levels)
    assert list(table.columns[:7]) == list(ADAPTATION_BASE_COLUMNS)
    assert list(table.columns[7:9]) == ["share_low", "share_high"]
    assert list(table.columns[9:]) == [f"trust_{i}" for i in range(1, 6)]
    first = table.iloc[0]
    answers = dataset.responses[
        (dataset.responses["participant"] == first["participant"])
        & (dataset.responses["session"] == first["session"])
        & (dataset.responses["item"] == "trust_5")
    ]["value"]
    assert first["trust_5"] == 6 - answers.iloc[0]  # scored: the reverse key applied
    assert (table["share_low"] + table["share_high"]).to_numpy() == pytest.approx(1.0)
    sessions = table.groupby("participant", sort=False)["session"].apply(list)
    assert all(s == sorted(s) for s in sessions)
    empty = adaptation_trust_table(dataclasses.replace(dataset, steps=dataset.steps.iloc[0:0]))
    assert list(empty.columns) == list(ADAPTATION_BASE_COLUMNS) and empty.empty
