"""The personal data registry covers the whole schema: a table added with a key to a participant,
or a column added that can hold free text, fails here until the registry says how erasure,
anonymising, the participant's own copy and the pseudonymised export treat it.

The registry's effect on real data is checked where each feature is: erasure and retention scan
the whole database afterwards (tests/app/personal_data.py), the subject-access and pseudonymised
exports are read back."""

from __future__ import annotations

import dataclasses

from sqlalchemy import JSON, Column, ForeignKey, Integer, MetaData, String, Table, Text

from analysis.dataset import StudyDataset
from app.services.privacy import personal_data
from app.services.privacy.personal_data import NOT_PERSONAL, TABLES, Erased
from app.tables import Base


def _participant_keys(table: Table) -> list[str]:
    """Columns that point at a participant: a key to ``participant.id``, or a name saying so."""
    return [
        column.name
        for column in table.columns
        if any(key.column.table.name == "participant" for key in column.foreign_keys)
        or "participant" in column.name
    ]


def _free_text(table: Table) -> set[str]:
    """Columns that can hold words (or anything) a participant gave: long text and JSON."""
    found = set()
    for column in table.columns:
        kind = column.type
        if isinstance(kind, Text | JSON) or (
            isinstance(kind, String) and (kind.length is None or kind.length >= 100)
        ):
            found.add(column.name)
    return found


def registry_problems(metadata: MetaData) -> list[str]:
    """Everything in ``metadata`` the registry does not account for, one line each."""
    registered = {entry.name: entry for entry in TABLES}
    not_personal = {str(cls.__table__.name): why for cls, why in NOT_PERSONAL.items()}  # type: ignore[attr-defined]
    problems = []
    for table in metadata.sorted_tables:
        keys = _participant_keys(table)
        if table.name in registered:
            entry = registered[table.name]
            declared = set(entry.free_text)
            for column in (*entry.cleared, *entry.naming):
                if column not in table.columns:
                    problems.append(f"{table.name}.{column}: named in the registry, not a column")
            if entry.subject_access is None and not entry.not_in_subject_access:
                problems.append(f"{table.name}: not in the participant's copy, and no reason")
            if entry.subject_access not in (None, *personal_data.SUBJECT_ACCESS_SECTIONS):
                problems.append(f"{table.name}: no section {entry.subject_access!r}")
            deleted = entry.erased == Erased.DELETED or entry.anonymised.value == "deleted"
            if deleted and "participant_id" not in table.columns:
                problems.append(f"{table.name}: deleted by participant_id, which it lacks")
        elif table.name in not_personal:
            if keys:
                problems.append(
                    f"{table.name}: has a participant key ({', '.join(keys)}) but is listed as "
                    "holding no personal data"
                )
            declared = set(not_personal[table.name].free_text)
        else:
            problems.append(
                f"{table.name}: not in the personal data registry "
                "(app.services.privacy.personal_data)"
                + (f"; participant key {', '.join(keys)}" if keys else "")
            )
            continue
        for column in sorted(_free_text(table) - declared):
            problems.append(f"{table.name}.{column}: free text the registry does not declare")
        for column in sorted(declared - set(table.columns.keys())):
            problems.append(f"{table.name}.{column}: declared in the registry, not a column")
    return problems


def test_every_table_and_free_text_column_is_in_the_registry() -> None:
    assert registry_problems(Base.metadata) == []


def test_a_new_table_with_a_participant_key_or_free_text_is_caught() -> None:
    """What the sweep is for: a scratch table, and a scratch column on a known table."""
    metadata = MetaData()
    for table in Base.metadata.tables.values():
        table.to_metadata(metadata)
    Table(
        "scratch_note",
        metadata,
        Column("id", Integer, primary_key=True),
        Column("participant_id", ForeignKey("participant.id")),
    )
    metadata.tables["study"].append_column(Column("scratch_notes", Text))
    assert registry_problems(metadata) == [
        "study.scratch_notes: free text the registry does not declare",
        "scratch_note: not in the personal data registry (app.services.privacy.personal_data); "
        "participant key participant_id",
    ]


def test_the_pseudonymised_export_covers_every_frame_with_participants() -> None:
    """Every table frame of the exported dataset carries a ``participant`` column; the
    pseudonymised export replaces it in each frame the registry names, so they must be all."""
    frames = {f.name for f in dataclasses.fields(StudyDataset) if f.type == "pd.DataFrame"}
    assert frames == set(personal_data.exported_frames()) == {"participants", "responses", "steps"}


def test_every_copy_the_audit_log_records_is_a_registered_file() -> None:
    kinds = personal_data.copy_actions()
    assert set(kinds) == {
        "db.backed_up",
        "export.written",
        "export.downloaded",
        "participant.exported",
    }
