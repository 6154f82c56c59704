"""The codebook: what every exported column means, its type, allowed values and source.

Generated from the same specifications that score and export the data, so a translated or
adapted instrument is documented exactly as it was administered.
"""

from __future__ import annotations

from typing import Any

import pandas as pd

from analysis.dataset import QUALITY_COLUMNS, StudyDataset
from analysis.exports.csvfile import CSV_TEXT_RULE
from analysis.exports.tables import (
    LONG_COLUMNS,
    WideColumn,
    steps_columns,
    wide_columns,
    with_attributes,
)
from analysis.instruments import InstrumentSpec, ItemSpec
from analysis.scoring import ScaleSpec

__all__ = ["CODEBOOK_COLUMNS", "codebook_json", "codebook_table"]

CODEBOOK_COLUMNS = (
    "file",
    "column",
    "label",
    "type",
    "measure",
    "allowed",
    "value_labels",
    "reverse_keyed",
    "instrument",
    "item",
    "session",
    "derivation",
    "citation",
)
"""Columns of :func:`codebook_table` (a study in several languages adds two per further
language: see :func:`translation_columns`)."""


def translation_columns(dataset: StudyDataset) -> list[str]:
    """``label_<code>`` and ``citation_<code>`` for each further language of the study: an
    item's wording as that language's participants read it, and the translation's source."""
    return [
        f"{kind}_{code}"
        for code in dataset.protocol.get("languages", [])[1:]
        for kind in ("label", "citation")
    ]


def _translation_citation(translation: dict[str, Any], citation: str) -> str:
    """The translated instrument's citation and where the translation comes from."""
    source = translation.get("source") or "the protocol does not say where it comes from"
    return f"{citation} Translation: {source}" if citation else f"Translation: {source}"


def _translated(dataset: StudyDataset, instrument: str, item: str | None) -> dict[str, str]:
    """An item's (or, ``item`` None, an instrument's) translation columns of the codebook."""
    out = {}
    for code, translation in dataset.protocol.get("translations", {}).items():
        spec = translation.get("instruments", {}).get(instrument)
        if spec is None:  # not a protocol instrument (the consent record)
            continue
        if item is not None:
            out[f"label_{code}"] = spec.get("items", {}).get(item, "")
        out[f"citation_{code}"] = _translation_citation(translation, spec.get("citation", ""))
    return out


def _range(low: float | None, high: float | None) -> str:
    if low is None or high is None:
        return ""
    return f"{low:g}–{high:g}"


def _labels_text(item: ItemSpec) -> str:
    return "; ".join(f"{code}={label}" for code, label in item.value_labels)


def _item_entry(
    dataset: StudyDataset, column: WideColumn, spec: InstrumentSpec, item: ItemSpec, file: str
) -> dict[str, Any]:
    reversed_value = column.source == "reversed"
    kind = item.kind
    numeric = kind in ("likert", "numeric") or (
        kind == "categorical" and all(isinstance(c, int) for c, _ in item.value_labels)
    )
    if kind == "categorical":
        allowed = ", ".join(str(code) for code, _ in item.value_labels) or "any code"
    elif kind == "text":
        allowed = "free text"
    else:
        allowed = _range(item.minimum, item.maximum)
    label = item.text if not spec.stem else f"{spec.stem} {item.text}"
    if reversed_value:
        label += " (reverse-scored)"
    if column.session is not None:
        label += f" [session {column.session}]"
    if item.expected is not None:
        label += f" (attention check: expected {item.expected})"
    reverse = ""
    if item.reverse and item.minimum is not None and item.maximum is not None:
        reverse = f"yes: scored {item.minimum + item.maximum:g} − x"
    return {
        "file": file,
        "column": column.name,
        "label": label,
        "type": "numeric" if numeric or reversed_value else "string",
        "measure": {"likert": "ordinal", "numeric": "scale"}.get(kind, "nominal"),
        "allowed": allowed,
        # A reversed column's numbers no longer mean the anchors' labels: no value labels.
        "value_labels": "" if reversed_value else _labels_text(item),
        "reverse_keyed": reverse,
        "instrument": spec.name,
        "item": item.key,
        "session": column.session,
        "derivation": (
            f"{item.minimum:g} + {item.maximum:g} − {item.key}"
            if reversed_value and item.minimum is not None and item.maximum is not None
            else ""
        ),
        "citation": spec.citation,
        **_translated(dataset, spec.name, item.key),
    }


def _scale_entry(column: WideColumn, scale: ScaleSpec) -> dict[str, Any]:
    keyed = [f"{key} (reversed)" if key in scale.reverse else key for key in scale.items]
    low, high = scale.score_range
    label = scale.label or scale.name
    if column.session is not None:
        label += f" [session {column.session}]"
    return {
        "file": "wide",
        "column": column.name,
        "label": label,
        "type": "numeric",
        "measure": "scale",
        "allowed": _range(low, high),
        "value_labels": "",
        "reverse_keyed": "",
        "instrument": scale.instrument,
        "item": "",
        "session": column.session,
        "derivation": (
            f"{scale.method} of {', '.join(keyed)}; reversed items scored "
            f"{scale.scale_min:g} + {scale.scale_max:g} − x; empty unless every item is answered"
        ),
        "citation": scale.citation,
    }


PSEUDONYM_LABEL = (
    "Participant pseudonym (a keyed hash of the code, the same in every file of this study; "
    "the key stays with the lab)"
)


def _participant_label(dataset: StudyDataset) -> str:
    """What the participant column holds: the lab's codes, or pseudonyms."""
    if dataset.manifest.get("participants") == "pseudonymised":
        return PSEUDONYM_LABEL
    return "Participant code"


def _participant_entries(dataset: StudyDataset, columns: list[WideColumn]) -> list[dict[str, Any]]:
    conditions = "; ".join(f"{c['code']}={c['label']}" for c in dataset.protocol["conditions"])
    fixed = {
        "participant": (_participant_label(dataset), "string", "nominal", "", ""),
        "condition": ("Experimental condition", "string", "nominal", conditions, ""),
        "status": ("Participant status at export", "string", "nominal", "", ""),
        "language": (LANGUAGE_LABEL, "string", "nominal", "", ""),
        "site": (SITE_LABEL, "string", "nominal", "", ""),
        **{
            name: (label, kind, "scale" if kind == "numeric" else "nominal", "", "")
            for name, (label, kind) in QUALITY_COLUMNS.items()
        },
    }
    out = []
    for column in columns:
        if column.source != "participant":
            continue
        label, kind, measure, labels, allowed = fixed.get(
            column.name, (f"Participant attribute '{column.key}'", "string", "nominal", "", "")
        )
        out.append(
            {
                "file": "wide",
                "column": column.name,
                "label": label,
                "type": kind,
                "measure": measure,
                "allowed": allowed,
                "value_labels": labels,
                "reverse_keyed": "",
                "instrument": "",
                "item": "",
                "session": None,
                "derivation": "",
                "citation": "",
            }
        )
    return out


LANGUAGE_LABEL = "Language the participant took part in (ISO 639 code)"
SITE_LABEL = "Site the participant was enrolled at (the protocol's [sites] names)"

_LONG = {
    "participant": ("Participant code", "string"),
    "condition": ("Experimental condition", "string"),
    "language": (LANGUAGE_LABEL, "string"),
    "site": (SITE_LABEL, "string"),
    "instrument": ("Instrument key", "string"),
    "session": ("Session number (empty for once-only instruments)", "integer"),
    "item": ("Item key (see the wide file's codebook rows for the wording)", "string"),
    "value": ("Raw answer as stored", "mixed"),
    "scored": (
        "Answer after the reverse key; empty for categorical and free-text items",
        "numeric",
    ),
}

_STEPS = {
    "participant": ("Participant code", "string"),
    "condition": ("Experimental condition", "string"),
    "language": (LANGUAGE_LABEL, "string"),
    "site": (SITE_LABEL, "string"),
    "category": ("Mental-activity category of the question", "string"),
    "session": ("Session number", "integer"),
    "run": ("Run within the session", "integer"),
    "iteration": ("Adaptation iteration within participant × category (1..N)", "integer"),
    "action": ("Index of the question asked (0-based arm)", "integer"),
    "answer": ("Participant's answer (1 = yes, 0 = no)", "integer"),
    "reward": ("Reward given to the learner", "numeric"),
    "preferred_arm": ("Protocol's preferred question of the category (0-based arm)", "integer"),
    "p_preferred_before": ("Probability of the preferred question before the answer", "numeric"),
    "p_preferred_after": ("Probability of the preferred question after the update", "numeric"),
    "modality": ("How the answer was given: key, button, speech or wizard", "string"),
    "transcript": ("Spoken answers: the words the recogniser heard", "string"),
    "transcript_confidence": ("Spoken answers: the recogniser's confidence (0-1)", "numeric"),
    "transcript_engine": ("Spoken answers: the recogniser (name and version)", "string"),
}


def _plain_entry(file: str, column: str, label: str, kind: str) -> dict[str, Any]:
    return {
        "file": file,
        "column": column,
        "label": label,
        "type": kind,
        "measure": "scale" if kind == "numeric" else "nominal",
        "allowed": "0–1" if column.startswith("p_") else "",
        "value_labels": "",
        "reverse_keyed": "",
        "instrument": "",
        "item": "",
        "session": None,
        "derivation": "",
        "citation": "",
    }


def codebook_table(dataset: StudyDataset) -> pd.DataFrame:
    """One row per exported column of the wide, long and steps files.

    Columns :data:`CODEBOOK_COLUMNS`: the file (``wide``, ``long``, ``steps``), column name,
    label (item wording as administered), type, SPSS measure level, allowed values, value
    labels (``1=Strongly disagree; …``), reverse key, instrument, item, session, how a derived
    column is computed, and the instrument's citation. A study in several languages adds, for
    each further language, the item's wording in it (``label_sv``) and the translated
    instrument's citation with the translation's source (``citation_sv``). The derivation of
    every column that can hold text states the CSV files' formula rule
    (:data:`~analysis.exports.csvfile.CSV_TEXT_RULE`).
    """
    columns = wide_columns(dataset)
    specs = {
        (spec.name, item.key): (spec, item) for spec in dataset.instruments for item in spec.items
    }
    scales = {scale.name: scale for scale in dataset.scales}
    rows = _participant_entries(dataset, columns)
    for column in columns:
        if column.source in ("raw", "reversed"):
            spec, item = specs[(column.instrument, column.key)]
            rows.append(_item_entry(dataset, column, spec, item, "wide"))
        elif column.source == "scale":
            rows.append(_scale_entry(column, scales[column.key]))
    participant = (_participant_label(dataset), "string")
    rows += [
        _plain_entry("long", c, *(participant if c == "participant" else _LONG[c]))
        for c in with_attributes(LONG_COLUMNS, dataset)
    ]
    rows += [
        _plain_entry("steps", c, *(participant if c == "participant" else _STEPS[c]))
        for c in steps_columns(dataset)
    ]
    arms = max((len(q) for q in dataset.protocol["categories"].values()), default=0)
    for when, text in (("before", "before the answer"), ("after", "after the update")):
        rows += [
            _plain_entry("steps", f"p_{when}_{j}", f"Probability of arm {j} {text}", "numeric")
            for j in range(arms)
        ]
    if dataset.protocol.get("record_audio"):
        rows.append(_recordings_entry())
    out = pd.DataFrame(rows, columns=[*CODEBOOK_COLUMNS, *translation_columns(dataset)])
    out["session"] = out["session"].astype("Int64")
    out[translation_columns(dataset)] = out[translation_columns(dataset)].fillna("")
    return _with_csv_rule(out)


def _recordings_entry() -> dict[str, Any]:
    """The recorded voices of a study that records them (``[speech] record_audio``): not in the
    exported files, but part of the study's data, so the codebook says where they are."""
    entry = _plain_entry(
        "recordings",
        "wav",
        "The participant's voice for each spoken answer: the utterance the answer was "
        "recognised from (WAV, 16 kHz, mono, 16-bit)",
        "binary",
    )
    entry["derivation"] = (
        "Kept in the database table answer_audio, one row per recognised spoken answer "
        "(answer_id, participant_id, wav, seconds, recorded_at); unclear attempts are not kept."
    )
    return entry


def _with_csv_rule(book: pd.DataFrame) -> pd.DataFrame:
    """State the CSV text rule where it applies: in every column that can hold text."""
    text = book["type"].isin(("string", "mixed"))
    book.loc[text, "derivation"] = [
        f"{derivation} {CSV_TEXT_RULE}" if derivation else CSV_TEXT_RULE
        for derivation in book.loc[text, "derivation"]
    ]
    return book


def _instrument_translations(dataset: StudyDataset, instrument: str) -> dict[str, Any]:
    """Language → the instrument's ``title``, ``citation`` and ``items`` in it."""
    return {
        code: translation["instruments"][instrument]
        for code, translation in dataset.protocol.get("translations", {}).items()
        if instrument in translation.get("instruments", {})
    }


def codebook_json(dataset: StudyDataset) -> dict[str, Any]:
    """The codebook as a JSON-able dict: study, instruments, and the columns of each file.

    ``{"study", "protocol_version", "languages", "translations": {code: {"source"}},
    "instruments": [{"name", "label", "citation", "stem", "per_session", "translations":
    {code: {"title", "citation", "items": {key: text}}}, "items": [{"key", "text", "kind",
    "minimum", "maximum", "reverse",
    "value_labels": {code: label}}]}], "scales": [...], "files": {"wide": [...], "long": [...],
    "steps": [...]}}``; file entries have the keys of :data:`CODEBOOK_COLUMNS` (``session``
    null when not per session). ``csv_text_cells`` states how the CSV files write text cells that
    a spreadsheet would run as formulas (:data:`~analysis.exports.csvfile.CSV_TEXT_RULE`).
    """
    table = codebook_table(dataset)
    files: dict[str, list[dict[str, Any]]] = {}
    for record in table.to_dict("records"):
        record["session"] = None if pd.isna(record["session"]) else int(record["session"])
        files.setdefault(record.pop("file"), []).append(record)
    return {
        "study": dataset.protocol["study"],
        "protocol_version": dataset.protocol.get("version", ""),
        "conditions": [dict(c) for c in dataset.protocol["conditions"]],
        "participants": dataset.manifest.get("participants", "codes"),
        "csv_text_cells": CSV_TEXT_RULE,
        "languages": list(dataset.protocol.get("languages", [])),
        "translations": {
            code: {"source": translation.get("source", "")}
            for code, translation in dataset.protocol.get("translations", {}).items()
        },
        "instruments": [
            {
                "name": spec.name,
                "label": spec.label,
                "citation": spec.citation,
                "stem": spec.stem,
                "per_session": spec.per_session,
                "translations": _instrument_translations(dataset, spec.name),
                "items": [
                    {
                        "key": item.key,
                        "text": item.text,
                        "kind": item.kind,
                        "minimum": item.minimum,
                        "maximum": item.maximum,
                        "reverse": item.reverse,
                        "value_labels": {str(code): label for code, label in item.value_labels},
                    }
                    for item in spec.items
                ],
            }
            for spec in dataset.instruments
        ],
        "scales": [
            {
                "name": scale.name,
                "label": scale.label,
                "instrument": scale.instrument,
                "items": list(scale.items),
                "reverse": sorted(scale.reverse),
                "scale_min": scale.scale_min,
                "scale_max": scale.scale_max,
                "method": scale.method,
                "citation": scale.citation,
            }
            for scale in dataset.scales
        ],
        "files": files,
    }
