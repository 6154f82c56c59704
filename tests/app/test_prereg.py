"""``trustlab prereg``: the bundle (protocol and its hash, hypotheses, plan, power, versions,
seeds; owner-only, never over a file without --force, audited), and the report saying whether
its analyses are the registered ones or listing each deviation."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import stat
from pathlib import Path

import pytest
from sqlalchemy import select
from typer.testing import CliRunner, Result

from analysis.mixed_models import analyse_mixed_models
from analysis.prereg import ALPHA, check_registration
from analysis.report import build_report
from analysis.specification import analysis_specification
from analysis.study import analyse_study
from app.cli import cli
from app.db import Database
from app.protocol import parse_protocol
from app.services import studies
from app.services.analysis_views import registrations, study_data
from app.services.audit import Actor
from app.services.participants.enrolment import enroll_participant
from app.services.privacy.sites import Scope
from app.tables import AuditEvent
from bench.seed import seed_study
from tests.conftest import sqlite_only
from tests.preloaded import REPO_ROOT

POWER = ["--effect", "interaction", "--eta2", ".204", "--convention", "spss", "--n", "24"]


def _run(database_url: str, *args: str) -> Result:
    return CliRunner().invoke(cli, list(args), env={"TRUSTLAB_DATABASE_URL": database_url})


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@sqlite_only("files and one audit row: the database only supplies the study")
def test_the_bundle_holds_protocol_plan_power_versions_and_seeds(
    database: Database, database_url: str, study_name: str, tmp_path: Path
) -> None:
    out = tmp_path / "prereg"
    written = _run(database_url, "prereg", "--study", study_name, "--out", str(out), *POWER)
    assert written.exit_code == 0, written.output
    assert sorted(p.name for p in out.iterdir()) == [
        "prereg.html",
        "prereg.json",
        "prereg.md",
        "protocol.toml",
    ]
    assert all(_mode(p) == 0o600 for p in out.iterdir()) and _mode(out) == 0o700
    registration = json.loads((out / "prereg.json").read_text())
    with database.read_session() as db:
        study = studies.get_study(db, study_name)
        digest, source = study.protocol_sha256, study.protocol_source
        protocol_summary = study_data.load_dataset(
            db, study=study, scope=Scope.every_site()
        ).protocol
    protocol = (out / "protocol.toml").read_text()
    assert protocol == source and hashlib.sha256(protocol.encode()).hexdigest() == digest
    assert registration["protocol"] == {"sha256": digest, "source": source}
    plan = registration["analysis_plan"]
    assert plan["primary_measure"] == "trust_1" and plan["measures"][0]["key"] == "trust_1"
    assert [m["key"] for m in plan["measures"] if m["reverse_keyed"]] == ["trust_5"]
    assert plan["models"] == [a.description for a in analysis_specification(protocol_summary)]
    assert plan["analyses"] == [a.to_dict() for a in analysis_specification(protocol_summary)]
    assert plan["alpha"] == ALPHA and plan["ss_type"] == 3
    assert plan["exclusions"]["statuses"] == ["withdrawn"]
    hypotheses = registration["hypotheses"]
    assert hypotheses[0].startswith("H1 (condition × session): the change of trust_1")
    power = registration["power_analysis"]  # the seed paper's interaction "as in SPSS", N = 24
    assert (power["n_total"], round(power["power"], 3), power["df2"]) == (24, 0.933, 66)
    assert {"trustlab", "numpy", "scipy", "pingouin"} <= set(registration["software"])
    assert len(registration["seeds"]["allocation_seed_sha256"]) == 64
    markdown = (out / "prereg.md").read_text()
    for heading in ("Hypotheses", "Planned analyses", "Exclusion rules", "Sample size and power"):
        assert f"## {heading}" in markdown
    assert digest in markdown and "N = 24 in total, power 0.9331 (λ = 16.91" in markdown
    assert "<h2>Protocol</h2>" in (out / "prereg.html").read_text()
    with database.read_session() as db:
        events = select(AuditEvent).where(AuditEvent.action == registrations.ACTION)
        event = db.scalars(events).one()
    assert event.details["sha256"] == hashlib.sha256((out / "prereg.json").read_bytes()).hexdigest()
    assert event.details["registration"]["analysis_plan"] == plan
    again = _run(database_url, "prereg", "--study", study_name, "--out", str(out))
    assert again.exit_code == 2
    assert again.stderr == (
        f"error: {out / 'prereg.json'} exists; choose another folder, or --force to replace it\n"
    )
    forced = _run(database_url, "prereg", "--study", study_name, "--out", str(out), "--force")
    assert forced.exit_code == 0, forced.output
    assert json.loads((out / "prereg.json").read_text())["power_analysis"] is None
    assert "no power analysis registered" in forced.stderr


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--power-json", "x.json", "--effect", "within"], "not both"),
        (["--f", "0.2"], "--f describes a power analysis: add --effect"),
        (["--effect", "within", "--f", "0.2", "--rho", "1.5", "--n", "24"], "rho"),
        (["--power-json", "missing.json"], "--power-json missing.json"),
    ],
    ids=["both", "no-effect", "rho", "missing"],
)
@sqlite_only("refused before anything is written")
def test_bad_power_input_is_one_line_and_writes_nothing(
    database_url: str, study_name: str, tmp_path: Path, args: list[str], words: str
) -> None:
    out = tmp_path / "prereg"
    refused = _run(database_url, "prereg", "--study", study_name, "--out", str(out), *args)
    assert refused.exit_code == 2 and refused.stderr.startswith("error: ")
    assert words in refused.stderr and refused.stderr.count("\n") == 1
    assert not out.exists()


@sqlite_only("the report reads the registration the audit log recorded; files otherwise")
def test_the_report_says_as_registered_or_lists_each_deviation(
    database: Database, database_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seed_study(database, name="small", participants=4, seed=5)
    out = tmp_path / "prereg"
    power = tmp_path / "power.json"
    answer = _run(database_url, "power", *POWER, "--groups", "2", "--sessions", "4", "--json")
    power.write_text(answer.stdout)
    written = _run(
        database_url, "prereg", "--study", "small", "--out", str(out), "--power-json", str(power)
    )
    assert written.exit_code == 0, written.output
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, scope=Scope.every_site(), study=studies.get_study(db, "small")
        )
    assert dataset.registration is not None  # the newest registration, from the audit log
    assert "in the audit log" in dataset.registration_source
    result = analyse_study(dataset)
    mixed = analyse_mixed_models(result)
    page = build_report(result, mixed=mixed)
    assert "<strong>As registered.</strong>" in page and "Deviations" not in page
    # A registration that differs: another protocol, a measure dropped, another α.
    registered = json.loads((out / "prereg.json").read_text())
    plan = registered["analysis_plan"]
    plan["protocol_sha256"] = "0" * 64
    plan["measures"] = plan["measures"][1:]
    plan["primary_measure"] = plan["measures"][0]["key"]
    plan["alpha"] = 0.01
    check = check_registration(registered, result, mixed=mixed)
    assert check.deviations == [
        f"protocol: registered SHA-256 000000000000…, the study's is "
        f"{result.dataset.manifest['protocol_sha256'][:12]}… (the protocol changed)",
        "measures analysed but not registered: trust_1",
        "primary measure: registered trust_2, reported first trust_1",
        "α: registered 0.01, used 0.05",
    ]
    edited = tmp_path / "edited.json"
    edited.write_text(json.dumps(registered))
    exported = _run(
        database_url,
        "export",
        "--study",
        "small",
        "--format",
        "html",
        "--out",
        str(tmp_path / "report.html"),
        "--prereg",
        str(edited),
    )
    assert exported.exit_code == 0, exported.output
    html_report = (tmp_path / "report.html").read_text()
    assert "Deviations from the pre-registration" in html_report
    assert "edited.json, SHA-256" in html_report
    assert "α: registered 0.01, used 0.05" in html_report
    plain = dataclasses.replace(dataset, registration=None)
    assert 'id="registration"' not in build_report(analyse_study(plain))


def _registration_section(page: str) -> str:
    start = page.index('<section id="registration">')
    return page[start : page.index("</section>", start)]


@sqlite_only("files and one audit row: the database only supplies the study")
def test_a_registration_after_data_collection_began_says_so_everywhere(
    database: Database, database_url: str, tmp_path: Path
) -> None:
    """Item 15: registering once participants are enrolled is recorded (how many, how many had
    answered), printed, written into prereg.json/.md/.html and repeated by the report instead
    of a bare "As registered"."""
    seed_study(database, name="small", participants=4, seed=5)
    with database.writing() as db:  # a fifth, enrolled but not yet answered
        enroll_participant(db, study_name="small", actor=Actor.system(), code="P900")
    out = tmp_path / "prereg"
    written = _run(database_url, "prereg", "--study", "small", "--out", str(out))
    assert written.exit_code == 0, written.output
    registration = json.loads((out / "prereg.json").read_text())
    assert registration["data_at_registration"] == {
        "participants_enrolled": 5,
        "participants_answered": 4,
    }
    sentence = (
        f"Registered on {registration['created_at']}, after 5 participants had been enrolled "
        "and 4 had answered (data collection had begun)."
    )
    assert f"note: {sentence} The registration says so.\n" in written.stderr
    assert f"- {sentence}" in (out / "prereg.md").read_text()
    assert f"<li>{sentence}</li>" in (out / "prereg.html").read_text()
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, study=studies.get_study(db, "small"), scope=Scope.every_site()
        )
    assert dataset.registration is not None
    assert dataset.registration["data_at_registration"] == registration["data_at_registration"]
    result = analyse_study(dataset)
    section = _registration_section(build_report(result, mixed=analyse_mixed_models(result)))
    assert f"<strong>As registered.</strong> {sentence}" in section


@sqlite_only("files and one audit row: the database only supplies the study")
def test_a_registration_before_any_participant_says_that_and_prints_no_note(
    database: Database, database_url: str, study_name: str, tmp_path: Path
) -> None:
    out = tmp_path / "prereg"
    written = _run(database_url, "prereg", "--study", study_name, "--out", str(out))
    assert written.exit_code == 0, written.output
    assert "enrolled" not in written.stderr
    registration = json.loads((out / "prereg.json").read_text())
    assert registration["data_at_registration"] == {
        "participants_enrolled": 0,
        "participants_answered": 0,
    }
    sentence = f"Registered on {registration['created_at']}, before any participant was enrolled."
    assert f"- {sentence}" in (out / "prereg.md").read_text()
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, study=studies.get_study(db, study_name), scope=Scope.every_site()
        )
    section = _registration_section(build_report(analyse_study(dataset)))
    assert sentence in section
    # An older registration, without the record, does not pretend to know.
    older = {
        k: v for k, v in dict(dataset.registration or {}).items() if k != "data_at_registration"
    }
    page = build_report(analyse_study(dataclasses.replace(dataset, registration=older)))
    assert "the registration does not record how much data there was" in page


@sqlite_only("files and one audit row: the database only supplies the study")
def test_a_study_in_two_languages_registers_the_language_covariate_it_fits(
    database: Database, database_url: str, tmp_path: Path
) -> None:
    """Item 16: the shipped English + Swedish protocol registers the linear mixed models with
    language, as the fitting code fits them, before any participant has chosen a language."""
    with database.writing() as db:
        loaded = parse_protocol(
            (REPO_ROOT / "app/protocols/fast_adaptation_trust_sv.toml").read_text()
        )
        studies.create_study(db, name="sv", loaded=loaded, actor=Actor.system("tests"))
    out = tmp_path / "prereg"
    written = _run(database_url, "prereg", "--study", "sv", "--out", str(out))
    assert written.exit_code == 0, written.output
    plan = json.loads((out / "prereg.json").read_text())["analysis_plan"]
    lmm = next(a for a in plan["analyses"] if a["name"] == "lmm")
    assert lmm["covariates"] == ["language"]
    assert lmm["formulas"] == [
        "{dv} ~ condition * session + language + (1 | participant)",
        "{dv} ~ condition * session + language + (1 + session_step | participant)",
    ]
    markdown = (out / "prereg.md").read_text()
    assert "linear mixed models: value ~ condition * session + language + (1 | participant)" in (
        markdown
    )
    assert "adjusted for language" in markdown
    with database.read_session() as db:
        protocol = study_data.load_dataset(
            db, study=studies.get_study(db, "sv"), scope=Scope.every_site()
        ).protocol
    assert protocol["languages"] == ["en", "sv"]
