"""Sites (app/services/privacy/sites.py): participants belong to a site, allocation can be
stratified by site, and an account limited to some sites never sees another site's participants —
swept over every staff route of the access policy, like the blinding sweep
(tests/app/test_blinding.py)."""

from __future__ import annotations

import csv
import difflib
import io
import json
import re
import threading
import time
import uuid
import zipfile
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from analysis.exports import EXPORT_FORMATS
from app.access import POLICY, Principal
from app.db import Database
from app.errors import Conflict, InvalidInput
from app.protocol import ProtocolError, parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.privacy import sites
from app.services.sessions import verify
from app.tables import (
    Allocation,
    AuditEvent,
    Participant,
    ParticipantStatus,
    Role,
    Study,
    User,
)
from bench.seed import seed_study
from tests.app.test_access_policy import app_routes
from tests.conftest import (
    EXP3_ONLY,
    Lab,
    UserClientFactory,
    client_of,
    fill_pre_study,
    protocol_text,
    sign_in_api,
    sqlite_only,
    tablet_client,
)

SITES = '[sites]\nnames = ["stockholm", "uppsala"]\nstratify = true\n\n[sites.labels]\n'
SITES += 'stockholm = "Stockholm (KTH)"\n\n[room]\n'
MINE, THEIRS = "stockholm", "uppsala"
THEIR_MARK = "uppsala-0"
"""What every code of the other site starts with (automatic codes at a site: SITE-001…)."""

SQLITE = sqlite_only("the filtering is one plain IN clause; migration 0019 is tested on both")


def sites_protocol(**replacements: str) -> str:
    return protocol_text(**EXP3_ONLY, **{"\n[room]\n": "\n" + SITES, **replacements})


def create_sites_study(database: Database, name: str = "multi", **replacements: str) -> str:
    with database.writing() as db:
        studies.create_study(
            db,
            name=name,
            loaded=parse_protocol(sites_protocol(**replacements)),
            actor=Actor.system(),
        )
    return name


def limit(database: Database, username: str, *names: str) -> None:
    with database.writing() as db:
        sites.set_user_sites(db, username=username, sites=list(names), actor=Actor.system())


def _station(
    admin: TestClient, client: TestClient, name: str, site: str | None = None
) -> TestClient:
    """A station (of ``site``; None: shared) and a robot client with a key for it."""
    created = admin.post("/api/v1/stations", json={"name": name, "site": site})
    assert created.status_code == 201, created.text
    key = admin.post(f"/api/v1/stations/{name}/devices", json={"label": name}).json()["key"]
    return client_of(client, headers={"Authorization": f"Bearer {key}"})


def _enrol(staff: TestClient, site: str, code: str | None = None) -> str:
    enrolled = staff.post("/api/v1/studies/multi/participants", json={"site": site, "code": code})
    assert enrolled.status_code == 201, enrolled.text
    assert enrolled.json()["site"] == site
    return str(enrolled.json()["code"])


@pytest.fixture
def world(
    app: FastAPI, client: TestClient, database: Database, user_client: UserClientFactory
) -> dict[str, Any]:
    """Study 'multi' at two sites. Stockholm: one participant seated at 'lab-sto' mid-session.
    Uppsala: two participants, one seated at 'lab-upp' with answers and a questionnaire, and
    an experimenter 'sto' and an analyst 'sto-analyst' limited to Stockholm."""
    create_sites_study(database)
    admin = user_client(Role.ADMIN, "pi")
    everyone = user_client(Role.EXPERIMENTER, "both")
    labs = {}
    for site, station in ((MINE, "lab-sto"), (THEIRS, "lab-upp")):
        robot = _station(admin, client, station)
        labs[site] = Lab(app, database, "multi", station, "", everyone, robot, {})
    codes: dict[str, list[str]] = {MINE: [], THEIRS: []}
    for site in (MINE, THEIRS, THEIRS):
        codes[site].append(_enrol(everyone, site))
    for site in (MINE, THEIRS):
        lab, code = labs[site], codes[site][0]
        seated = everyone.put(
            f"/api/v1/stations/{lab.station}/participant", json={"study": "multi", "code": code}
        )
        assert seated.status_code == 200, seated.text
        lab.tablets[code] = tablet_client(app, lab, code)
        fill_pre_study(lab.tablets[code])
        lab.start_session()  # familiarisation
        lab.run_session()
        lab.start_session()
        lab.run_session()
        lab.experimenter.post(f"/api/v1/stations/{lab.station}/sessions/current/end")
        lab.fill_pending_questionnaires()
    mine = user_client(Role.EXPERIMENTER, "sto")
    analyst = user_client(Role.ANALYST, "sto-analyst")
    limit(database, "sto", MINE)
    limit(database, "sto-analyst", MINE)
    return {"admin": admin, "mine": mine, "analyst": analyst, "codes": codes, "labs": labs}


def _staff_reads(role: Principal) -> list[str]:
    """Every page and read the access policy lets ``role`` fetch (a new route is swept without
    changing this test); event streams carry types only, tablet links need a token."""
    paths = []
    for (method, path), allowed in sorted(POLICY.items()):
        if method != "GET" or role not in allowed or Principal.ANONYMOUS in allowed:
            continue
        if path.endswith(("/events", "/speech/audio")):
            continue  # a preview's spoken line is a protocol line: no participant's anything
        paths.append(path)
    return paths


def _fill(path: str, *, station: str, code: str, export: str = "long-csv") -> str:
    return (
        path.replace(
            "{name}", station if path.startswith(("/stations", "/api/v1/stations")) else "multi"
        )
        .replace("{code}", code)
        .replace("{export}", export)
        .replace("{language}/{number}", "en/1")
        .replace("{language}", "en")
        .replace("{slug}", "study")
    )


def _texts(response: Any) -> list[str]:
    """The response's text, and every member's of a zip file."""
    if response.content[:2] == b"PK":
        with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
            return [archive.read(n).decode("utf-8", "replace") for n in archive.namelist()]
    return [response.content.decode("utf-8", "replace")]


@SQLITE
def test_a_site_limited_account_never_sees_another_sites_participants(
    world: dict[str, Any],
) -> None:
    mine_code = world["codes"][MINE][0]
    leaks: dict[str, str] = {}
    for role, staff in (
        (Principal.EXPERIMENTER, world["mine"]),
        (Principal.ANALYST, world["analyst"]),
    ):
        for path in _staff_reads(role):
            exports = list(EXPORT_FORMATS) if "{export}" in path else ["long-csv"]
            for export in exports:
                url = _fill(path, station="lab-sto", code=mine_code, export=export)
                response = staff.get(url)
                if response.status_code == 409 and export in ("steps-csv", "adaptation-csv"):
                    continue  # pragma: no cover - the study is not blinded
                assert response.status_code < 400, f"{role} {url}: {response.status_code}"
                if any(THEIR_MARK in text for text in _texts(response)):
                    leaks[f"{role} {url}"] = "an Uppsala code"
    assert leaks == {}, json.dumps(leaks, indent=1)

    experimenter = world["mine"]
    # counts: only Stockholm's one participant
    summary = experimenter.get("/api/v1/studies/multi").json()
    assert sum(g["active"] + g["withdrawn"] + g["completed"] for g in summary["enrolment"]) == 1
    listed = experimenter.get("/api/v1/studies/multi/participants").json()
    assert [p["code"] for p in listed] == [mine_code]
    assert [s["name"] for s in experimenter.get("/api/v1/stations").json()] == ["lab-sto"]
    # the dashboard's data is Stockholm's alone: the PI's, filtered to Stockholm
    pi = world["admin"]
    assert (
        experimenter.get("/studies/multi/dashboard.json").json()
        == pi.get("/studies/multi/dashboard.json?site=stockholm").json()
    )
    # and the analysis counts Stockholm's participants only
    analysed = re.compile(r"(\d+ participants? analysed)")
    own = analysed.findall(world["analyst"].get("/studies/multi/analysis").text)
    assert own == analysed.findall(pi.get("/studies/multi/analysis?site=stockholm").text)
    assert own != analysed.findall(pi.get("/studies/multi/analysis").text)
    everyone = pi.get("/studies/multi/dashboard.json").json()
    assert everyone["answers"] > experimenter.get("/studies/multi/dashboard.json").json()["answers"]


@SQLITE
def test_another_sites_participant_and_station_do_not_exist_for_a_limited_account(
    world: dict[str, Any], database: Database
) -> None:
    """Every staff route naming a participant of another site, or a station seating one,
    answers 404 as for an unknown one, and changes nothing."""
    theirs, unseated = world["codes"][THEIRS]
    staff = world["mine"]
    bodies: dict[str, Any] = {
        "/api/v1/studies/{name}/participants/{code}/withdraw": {"json": {"reason": "x"}},
        "/api/v1/studies/{name}/participants/{code}/erase": {"json": {"confirm": unseated}},
        "/studies/{name}/participants/{code}/withdraw": {
            "data": {"data": "erase", "confirm_code": unseated}
        },
        "/studies/{name}/participants/{code}/language": {"data": {"language": "en"}},
        "/api/v1/stations/{name}/participant": {"json": {"study": "multi", "code": theirs}},
        "/api/v1/stations/{name}/prompts": {"json": {"category": "conation"}},
        "/api/v1/stations/{name}/steps/{step_id}/answer": {
            "json": {"answer": "yes", "idempotency_key": "k"}
        },
        "/stations/{name}/assign": {"data": {"study": "multi", "code": theirs}},
        "/stations/{name}/study": {"data": {"study": "multi"}},
        "/stations/{name}/woz/prompt": {"data": {"category": "conation"}},
        "/stations/{name}/woz/answer": {
            "data": {"step_id": "1", "answer": "yes", "idempotency_key": "k"}
        },
    }
    swept = []
    for (method, path), allowed in sorted(POLICY.items()):
        if Principal.EXPERIMENTER not in allowed or Principal.ANONYMOUS in allowed:
            continue
        if path.endswith("/events") or not ("{code}" in path or "/stations/{name}" in path):
            continue
        url = _fill(path, station="lab-upp", code=unseated).replace("{step_id}", "1")
        options = bodies.get(path, {"data": {}} if not path.startswith("/api") else {})
        response = staff.request(method if method != "WS" else "GET", url, **options)
        assert response.status_code == 404, f"{method} {url}: {response.status_code}"
        assert THEIR_MARK not in response.text.replace(unseated, ""), url
        swept.append((method, path))
    assert ("POST", "/api/v1/studies/{name}/participants/{code}/erase") in swept
    assert ("POST", "/stations/{name}/session/start") in swept
    # seating another site's participant at one's own station is refused too
    seat = staff.put(
        "/api/v1/stations/lab-sto/participant", json={"study": "multi", "code": theirs}
    )
    assert seat.status_code == 404
    with database.read_session() as db:
        rows = db.scalars(select(Participant).where(Participant.site == THEIRS)).all()
        assert {p.status for p in rows} == {ParticipantStatus.ACTIVE}
        assert all(p.erased_at is None and p.locked_at is None for p in rows)
        assert {p.code for p in rows} == {theirs, unseated}
    # a limited analyst meets the station routes' own refusal first, as the access policy says
    assert world["analyst"].get("/stations/lab-upp").status_code == 403
    # the PI sees and may act on both sites
    assert world["admin"].get(f"/studies/multi/participants/{theirs}").status_code == 200


@SQLITE
def test_enrolment_at_a_site_refuses_clearly_and_stratifies_by_site(
    world: dict[str, Any], database: Database, database_url: str
) -> None:
    from tests.app.test_cli import run

    staff, everyone = world["mine"], world["labs"][MINE].experimenter
    refusals = [
        (everyone, {}, 422, "enrols each participant at a site: give one of stockholm, uppsala"),
        (
            everyone,
            {"site": "malmo"},
            422,
            "site 'malmo' is not a site of study 'multi': stockholm, uppsala",
        ),
        (staff, {"site": THEIRS}, 403, "limited to site stockholm: it cannot enrol at 'uppsala'"),
    ]
    with database.read_session() as db:
        before = len(db.scalars(select(Participant)).all())
    for who, body, status, words in refusals:
        refused = who.post("/api/v1/studies/multi/participants", json=body)
        assert refused.status_code == status and words in refused.json()["detail"], refused.text
    page = staff.post("/studies/multi/participants", data={"site": THEIRS})
    assert page.status_code == 403 and "cannot enrol at" in page.text
    with database.read_session() as db:
        assert len(db.scalars(select(Participant)).all()) == before  # nothing half-done
    code, _, err = run(database_url, "participant", "enroll", "--study", "multi")
    assert code != 0 and "give one of stockholm, uppsala" in err
    code, out, _ = run(database_url, "participant", "enroll", "--study", "multi", "--site", THEIRS)
    assert code == 0 and out.startswith("enrolled uppsala-003 in 'multi' at uppsala: condition")
    for _ in range(5):
        _enrol(staff, MINE)
    assert "Stockholm (KTH)" in staff.get("/studies/multi").text  # the site's label
    with database.read_session() as db:
        rows = db.scalars(select(Participant).where(Participant.study_id.is_not(None))).all()
        assert {p.stratum for p in rows} == {"site=stockholm", "site=uppsala"}
        assert all(p.strata == {"site": p.site} for p in rows)
        assert [p.code for p in rows if p.site == MINE][:2] == ["stockholm-001", "stockholm-002"]
        report = verify.verify_study(db, study_name="multi")
        assert report.ok, report


@SQLITE
def test_a_site_filtered_export_has_the_site_column_and_its_codebook_entry(
    world: dict[str, Any], database_url: str, tmp_path: Path
) -> None:
    pi, analyst = world["admin"], world["analyst"]
    rows = list(csv.DictReader(io.StringIO(pi.get("/studies/multi/exports/long-csv").text)))
    assert list(rows[0])[:4] == ["participant", "condition", "language", "site"]
    assert {r["site"] for r in rows} == {MINE, THEIRS}
    assert {r["participant"].split("-")[0] for r in rows} == {r["site"] for r in rows}
    own = analyst.get("/studies/multi/exports/long-csv").text
    assert own == pi.get("/studies/multi/exports/long-csv?site=stockholm").text
    assert {r["site"] for r in csv.DictReader(io.StringIO(own))} == {MINE}
    codebook = list(csv.DictReader(io.StringIO(pi.get("/studies/multi/exports/codebook-csv").text)))
    site_rows = {r["file"]: r["label"] for r in codebook if r["column"] == "site"}
    assert set(site_rows) == {"wide", "long", "steps"}
    assert all("Site the participant was enrolled at" in label for label in site_rows.values())
    from tests.app.test_cli import run

    code, out, _ = run(
        database_url,
        "export",
        "--study",
        "multi",
        "--format",
        "long-csv",
        "--out",
        str(tmp_path / "uppsala.csv"),
        "--site",
        THEIRS,
    )
    assert code == 0, out
    exported = list(csv.DictReader((tmp_path / "uppsala.csv").open()))
    assert {r["site"] for r in exported} == {THEIRS}
    other = analyst.get("/studies/multi/analysis?site=uppsala")
    assert other.status_code == 403 and "limited to site stockholm" in other.text
    unknown = pi.get("/studies/multi/dashboard.json?site=malmo")
    assert unknown.status_code == 422 and "has no site &#39;malmo&#39;" in unknown.text


@SQLITE
def test_limiting_an_account_refuses_what_would_silently_hide_everyone(
    world: dict[str, Any], database: Database, database_url: str
) -> None:
    from tests.app.test_cli import run

    with database.writing() as db:
        with pytest.raises(InvalidInput, match="no study declares site malmo"):
            sites.set_user_sites(db, username="both", sites=["malmo"], actor=Actor.system())
        db.rollback()
        with pytest.raises(Conflict, match="admins see every site"):
            sites.set_user_sites(db, username="pi", sites=[MINE], actor=Actor.system())
        db.rollback()
    code, _, err = run(database_url, "user", "sites", "both", "--site", "malmo")
    assert code != 0 and "no study declares site malmo (sites declared: stockholm, uppsala)" in err
    code, _, err = run(database_url, "user", "sites", "both")
    assert code != 0 and "give the sites (--site NAME, repeatable) or --all" in err
    code, out, _ = run(database_url, "user", "sites", "both", "--site", THEIRS, "--site", MINE)
    assert code == 0 and out.strip() == "'both' now sees sites stockholm, uppsala"
    code, out, _ = run(database_url, "user", "sites", "sto", "--all")
    assert code == 0 and out.strip() == "'sto' now sees every site"
    with database.read_session() as db:
        users = {u.username: u.sites for u in db.scalars(select(User))}
        assert users["both"] == [MINE, THEIRS] and users["sto"] is None
        changes = db.scalars(select(AuditEvent).where(AuditEvent.action == "user.sites_changed"))
        assert [e.subject for e in changes][-2:] == ["both", "sto"]
    # the account page sets it too, and the PI's page says what it does
    pi = world["admin"]
    page = pi.get("/admin/users/sto-analyst").text
    assert "only the participants of <strong>stockholm</strong>" in page
    done = pi.post("/admin/users/sto-analyst/sites", data={"every": "true"}, follow_redirects=False)
    assert done.status_code == 303
    assert "every site" in pi.get("/admin/users/sto-analyst").text
    # a limited account in a study without sites sees nobody there and may not enrol
    with database.writing() as db:
        studies.create_study(
            db,
            name="plain",
            loaded=parse_protocol(protocol_text(**EXP3_ONLY)),
            actor=Actor.system(),
        )
    assert pi.post("/api/v1/studies/plain/participants", json={}).status_code == 201
    # 'both' sees both sites: still a limit, and this study has none of them
    both = world["labs"][MINE].experimenter
    refused = both.post("/api/v1/studies/plain/participants", json={})
    assert refused.status_code == 403 and "has no sites" in refused.json()["detail"]
    assert both.get("/api/v1/studies/plain/participants").json() == []
    assert len(world["mine"].get("/api/v1/studies/plain/participants").json()) == 1  # now --all


def test_a_protocol_declares_sites_cleanly() -> None:
    def problems(**replacements: str) -> str:
        with pytest.raises(ProtocolError) as bad:
            parse_protocol(sites_protocol(**replacements))
        return str(bad.value)

    names = 'names = ["stockholm", "uppsala"]'
    assert "sites.names[1]: String should match pattern" in problems(
        **{names: 'names = ["stockholm", "Uppsala"]'}
    )
    message = problems(
        **{
            names: 'names = ["stockholm", "uppsala", "stockholm"]',
            "stratify_by = []": 'stratify_by = ["site"]',
            'stockholm = "Stockholm (KTH)"': 'malmo = "Malmö"',
        }
    )
    assert "sites.names[2]: duplicate site 'stockholm'" in message
    assert "allocation.stratify_by: a study with [sites] stratifies by site" in message
    assert "sites.labels.malmo: not listed in sites.names" in message
    protocol = parse_protocol(sites_protocol()).protocol
    assert protocol.sites is not None and protocol.sites.label("uppsala") == "uppsala"


# ------------------------------------------------ the sweep: nothing a limited account gets depends
# on another site

STREAMS = ("/studies/{name}/events", "/stations/{name}/events")
"""The staff's live streams: swept by reading them while the other site is busy."""

NOT_SWEPT_FOR_THE_OTHER_SITE = {
    "writes": "a change, not a read: naming another site's participant or a station seating one "
    "answers 404 (test_another_sites_participant_and_station_do_not_exist_for_a_limited_account)"
    ", and a typed code can only clash within its own site (test_a_code_in_use_at_another_site"
    "_is_not_told)",
    "admins": "admins see every site: an admin's account cannot be limited",
    "anonymous": "no account, so no scope: public pages carry no participant data (the tablet "
    "and kiosk links are the participant's own token; the room shell asks for a device key)",
    "devices": "a robot's key belongs to its station, which serves whoever is seated there",
    "participants": "a tablet token reaches its own participant only",
}
"""Why the routes the sweep does not read are not swept: by the access policy's principals, so a
new route falls into one of these, or is read by the sweep."""


def _classify(method: str, path: str) -> str:
    """``swept``, ``stream``, or the key of :data:`NOT_SWEPT_FOR_THE_OTHER_SITE`."""
    allowed = POLICY[(method, path)]
    if Principal.ANONYMOUS in allowed:
        return "anonymous"
    if allowed & {Principal.EXPERIMENTER, Principal.ANALYST}:
        if method != "GET":
            return "writes"
        return "stream" if path in STREAMS else "swept"
    if Principal.ADMIN in allowed:
        return "admins"
    if allowed & {Principal.DEVICE_OWN, Principal.DEVICE_OTHER}:
        return "devices"
    return "participants"


_VOLATILE = (
    (
        re.compile(r"\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}(?::\d{2}(?:\.\d+)?)?(?:Z|[+-]\d{2}:?\d{2})?"),
        "<when>",
    ),
    (re.compile(r"\d{2} [A-Z][a-z]{2} \d{2}\d{2}:\d{2}:\d{2}"), "<when>"),  # an SPSS file's header
    (re.compile(r"\b\d{1,2}:\d{2}:\d{2}\b"), "<time>"),
    (re.compile(r"since=[0-9.]+"), "since=<when>"),  # when a live page began to read
)


def _normalised(text: str) -> str:
    for pattern, replacement in _VOLATILE:
        text = pattern.sub(replacement, text)
    return text


def _run_at(lab: Lab, code: str) -> None:
    """Seat ``code`` at the lab's station and run the familiarisation and one session."""
    seated = lab.experimenter.put(
        f"/api/v1/stations/{lab.station}/participant", json={"study": lab.study, "code": code}
    )
    assert seated.status_code == 200, seated.text
    lab.tablets[code] = tablet_client(lab.app, lab, code)
    fill_pre_study(lab.tablets[code])
    for _ in range(2):
        lab.start_session()
        lab.run_session()
    lab.experimenter.post(f"/api/v1/stations/{lab.station}/sessions/current/end")
    lab.fill_pending_questionnaires()


class _Listener:
    """A limited account's live stream read in a thread until its login ends."""

    def __init__(self, client: TestClient, path: str) -> None:
        self.client, self.path, self.lines = client, path, []  # type: list[str]
        self.opened = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()
        assert self.opened.wait(10), f"{path} did not open"

    def _read(self) -> None:
        with self.client.stream("GET", self.path) as response:
            assert response.status_code == 200, self.path
            for line in response.iter_lines():
                self.opened.set()
                self.lines.append(line)

    def types(self) -> list[list[str]]:
        """Each message's event types, once the stream has ended."""
        self.thread.join(10)
        assert not self.thread.is_alive(), f"{self.path} did not end with its login"
        return [json.loads(line[6:])["types"] for line in self.lines if line.startswith("data: ")]


@SQLITE
def test_nothing_a_limited_account_reads_or_hears_depends_on_another_site(
    app: FastAPI,
    client: TestClient,
    database: Database,
    database_url: str,
    user_client: UserClientFactory,
    tmp_path: Path,
) -> None:
    """Every page, JSON read, export and stream a limited experimenter or analyst may use (the
    app's routes, by the access policy) answers the same, after the times are taken out, before
    and after another site enrols, runs sessions and answers questionnaires; its streams hear
    nothing of that site; and the command line's site option writes the same files."""
    from tests.app.test_cli import run

    create_sites_study(database)
    admin = user_client(Role.ADMIN, "pi")
    everyone = user_client(Role.EXPERIMENTER, "both")
    labs = {
        station: Lab(
            app,
            database,
            "multi",
            station,
            "",
            everyone,
            _station(admin, client, station, site),
            {},
        )
        for station, site in (("lab-sto", MINE), ("lab-upp", THEIRS), ("lab-3", None))
    }
    ours = [_enrol(everyone, MINE), _enrol(everyone, MINE)]
    _run_at(labs["lab-sto"], ours[0])
    readers = {
        Principal.EXPERIMENTER: user_client(Role.EXPERIMENTER, "sto"),
        Principal.ANALYST: user_client(Role.ANALYST, "sto-analyst"),
    }
    limit(database, "sto", MINE)
    limit(database, "sto-analyst", MINE)

    routes = sorted(app_routes(app))
    kinds = {route: _classify(*route) for route in routes}
    swept = [path for (method, path), kind in kinds.items() if kind == "swept"]
    assert {path for (_, path), kind in kinds.items() if kind == "stream"} == set(STREAMS)
    assert set(kinds.values()) <= {"swept", "stream", *NOT_SWEPT_FOR_THE_OTHER_SITE}
    assert "/studies/{name}/analysis/power" in swept and "/api/v1/stations" in swept

    def snapshot() -> dict[str, str]:
        app.state.activity.flush()  # robots' and logins' last contact, written now
        answers = {}
        for role, reader in readers.items():
            for path in swept:
                if role not in POLICY[("GET", path)]:
                    continue
                for export in list(EXPORT_FORMATS) if "{export}" in path else ["-"]:
                    url = _fill(path, station="lab-sto", code=ours[0], export=export)
                    response = reader.get(url)
                    texts = _texts(response) if response.status_code < 400 else [response.text]
                    answers[f"{role} {url}"] = "\n".join(
                        [str(response.status_code), *(_normalised(t) for t in texts)]
                    )
        for export in EXPORT_FORMATS:
            out = tmp_path / uuid.uuid4().hex / export
            code, _, err = run(
                database_url, "export", "--study", "multi", "--format", export,
                "--out", str(out), "--site", MINE,
            )  # fmt: skip
            files = sorted(out.rglob("*")) if out.is_dir() else [out] if out.exists() else []
            answers[f"cli export {export}"] = "\n".join(
                [str(code), _normalised(err)]
                + [_normalised(f.read_text("utf-8", "replace")) for f in files if f.is_file()]
            )
        return answers

    before = snapshot()
    # The limited experimenter's streams: the study's, and a free station's.
    listener = client_of(client)
    sign_in_api(listener, "sto")
    streams = [
        _Listener(listener, "/studies/multi/events"),
        _Listener(listener, "/stations/lab-3/events"),
    ]

    # Uppsala: enrolment, a session at its own station, and one at the free station.
    theirs = [_enrol(everyone, THEIRS), _enrol(everyone, THEIRS)]
    _run_at(labs["lab-upp"], theirs[0])
    _run_at(labs["lab-3"], theirs[1])
    assert everyone.delete("/api/v1/stations/lab-3/participant").status_code == 200
    time.sleep(0.3)  # longer than a stream's coalescing window: Uppsala's burst is over
    # What the streams must hear: Stockholm's second participant seated at the free station.
    seated = everyone.put(
        "/api/v1/stations/lab-3/participant", json={"study": "multi", "code": ours[1]}
    )
    assert seated.status_code == 200
    time.sleep(0.3)
    assert listener.post("/logout", follow_redirects=False).status_code == 303
    heard = [stream.types() for stream in streams]
    assert heard == [[["participant_assigned"]], [["participant_assigned"]]], heard
    # Back to Stockholm's state before; Uppsala's participants leave the stations they used.
    for station in ("lab-3", "lab-upp"):
        freed = everyone.delete(f"/api/v1/stations/{station}/participant")
        assert freed.status_code == 200, freed.text

    after = snapshot()
    differing = {key: _diff(before[key], after[key]) for key in before if before[key] != after[key]}
    assert differing == {}, json.dumps(differing, indent=1, ensure_ascii=False)
    # the sweep would have seen it: the PI's answers did change
    assert admin.get("/api/v1/studies/multi/participants").json()[-1]["code"] == theirs[-1]


def _diff(before: str, after: str) -> str:
    """The first lines that differ (for the failure message)."""
    lines = difflib.unified_diff(before.splitlines(), after.splitlines(), lineterm="", n=0)
    return "\n".join(list(lines)[2:12])


@SQLITE
def test_the_power_planning_of_a_limited_analyst_counts_its_sites_only(
    database: Database, user_client: UserClientFactory
) -> None:
    """The power page prefills ρ, ε, f and N from the participants the account may see."""
    create_sites_study(database)  # declares the sites the analyst is limited to
    seed_study(database, name="pilot", participants=20, seed=4)
    with database.writing() as db:
        rows = db.execute(
            select(Participant.id, Allocation.condition)
            .join(Allocation, Allocation.participant_id == Participant.id)
            .join(Study, Study.id == Participant.study_id)
            .where(Study.name == "pilot")
            .order_by(Participant.id)
        ).all()
        seen: dict[str, int] = {}
        for participant_id, condition in rows:  # every other one of each condition
            seen[condition] = seen.get(condition, 0) + 1
            site = MINE if seen[condition] % 2 else THEIRS
            db.execute(
                update(Participant).where(Participant.id == participant_id).values(site=site)
            )
        db.commit()
    mine = sum((n + 1) // 2 for n in seen.values())
    assert min(seen.values()) >= 8 and mine < len(rows)
    analyst = user_client(Role.ANALYST, "sto-analyst")
    limit(database, "sto-analyst", MINE)
    pi = user_client(Role.ADMIN, "pi")
    prefilled = re.compile(r"Prefilled from this study&#39;s own data: (\d+) complete participants")
    assert prefilled.findall(pi.get("/studies/pilot/analysis/power").text) == [str(len(rows))]
    own = analyst.get("/studies/pilot/analysis/power").text
    assert prefilled.findall(own) == [str(mine)]
    # the same as the analysis page of the account (which was already limited)
    assert prefilled.findall(analyst.get("/studies/pilot/analysis").text) == [str(mine)]


@SQLITE
def test_a_code_in_use_at_another_site_is_not_told(
    world: dict[str, Any], database_url: str
) -> None:
    """A typed code at a site begins with the site's name, so "already used" is only said of a
    participant the account sees: another site's code, used or not, gets one answer."""
    from tests.app.test_cli import run

    staff, everyone = world["mine"], world["labs"][MINE].experimenter
    used_there, used_here = world["codes"][THEIRS][0], world["codes"][MINE][0]
    answers = []
    for code in (used_there, "uppsala-999", "P001", "Q9"):
        refused = staff.post(
            "/api/v1/studies/multi/participants", json={"site": MINE, "code": code}
        )
        answers.append((refused.status_code, refused.json()["detail"].replace(code, "CODE")))
    assert (
        answers
        == [
            (
                422,
                "participant code 'CODE': a code at site 'stockholm' begins with 'stockholm-' "
                "(e.g. stockholm-017), or leave it out for the next one",
            )
        ]
        * 4
    )
    page = staff.post("/studies/multi/participants", data={"site": MINE, "code": used_there})
    assert page.status_code == 422 and "begins with &#39;stockholm-&#39;" in page.text
    # at its own site "already used" is said, of a participant the account sees
    clash = staff.post("/api/v1/studies/multi/participants", json={"site": MINE, "code": used_here})
    assert clash.status_code == 409 and "already used" in clash.json()["detail"]
    assert staff.get(f"/studies/multi/participants/{used_here}").status_code == 200
    # the rule is the study's, for every account and the command line alike
    assert (
        everyone.post(
            "/api/v1/studies/multi/participants", json={"site": THEIRS, "code": "stockholm-050"}
        ).status_code
        == 422
    )
    enrolled = staff.post(
        "/api/v1/studies/multi/participants", json={"site": MINE, "code": "stockholm-x7"}
    )
    assert enrolled.status_code == 201 and enrolled.json()["code"] == "stockholm-x7"
    code, _, err = run(
        database_url, "participant", "enroll", "--study", "multi", "--site", THEIRS,
        "--code", "u-1",
    )  # fmt: skip
    assert code != 0 and "a code at site 'uppsala' begins with 'uppsala-'" in err


def test_two_sites_may_not_share_the_start_of_their_codes() -> None:
    long = "university_hospital_north_wing"
    text = sites_protocol(
        **{'names = ["stockholm", "uppsala"]': f'names = ["{long}", "{long[:-4]}_east"]'}
    )
    with pytest.raises(ProtocolError, match="begin with the same 24 characters"):
        parse_protocol(text)
