"""Stations have a site (app.services.privacy.sites, ``station.site``): a station of a site is only
its site's, and a shared one shows a limited account its robots' contact only while one of its own
participants sits there. Run on SQLite and PostgreSQL; the sites sweep
(tests/app/test_sites.py) covers the station list with a station of each kind."""

from __future__ import annotations

from datetime import timedelta

from fastapi.testclient import TestClient
from sqlalchemy import select, text, update

from app import events, schema
from app.db import Database
from app.events import Event
from app.services.privacy import sites
from app.services.sessions import stations
from app.tables import AuditEvent, Device, Role, Station, utcnow
from tests.app.test_cli import run
from tests.app.test_schema import _insert_row
from tests.app.test_sites import MINE, THEIRS, _enrol, _station, create_sites_study, limit
from tests.conftest import UserClientFactory


def _heard(database: Database, station: str, minutes_ago: int) -> None:
    """The station's robot was last heard ``minutes_ago``, its notice then too."""
    when = utcnow() - timedelta(minutes=minutes_ago)
    with database.writing() as db:
        station_id = db.scalar(select(Station.id).where(Station.name == station))
        db.execute(
            update(Device)
            .where(Device.station_id == station_id)
            .values(last_seen_at=when, notice="battery low", notice_at=when)
        )
        db.commit()


def _devices(reader: TestClient, station: str) -> list[dict[str, object]]:
    found = [s for s in reader.get("/api/v1/stations").json() if s["name"] == station]
    assert len(found) == 1, found
    return list(found[0]["devices"])


def test_a_station_of_another_site_does_not_exist_for_a_limited_account(
    client: TestClient, database: Database, user_client: UserClientFactory
) -> None:
    """Not listed (API, page, archived count), and every route naming it answers 404, even
    while it is free; its own site and unlimited accounts see it."""
    create_sites_study(database)
    admin = user_client(Role.ADMIN, "pi")
    for name, site in (("lab-sto", MINE), ("lab-upp", THEIRS), ("lab-shared", None)):
        _station(admin, client, name, site)
    assert admin.post("/stations/lab-upp/archive", data={"archived": "true"}).status_code == 200
    _station(admin, client, "lab-upp-2", THEIRS)
    mine = user_client(Role.EXPERIMENTER, "sto")
    limit(database, "sto", MINE)
    everyone = user_client(Role.EXPERIMENTER, "both")

    listed = mine.get("/api/v1/stations").json()
    assert [(s["name"], s["site"]) for s in listed] == [("lab-shared", None), ("lab-sto", MINE)]
    page = mine.get("/stations").text
    assert "lab-upp" not in page and "archived station" not in page
    for url in ("/stations/lab-upp-2", "/stations/lab-upp-2/events",
                "/stations/lab-upp-2/room-panel", "/api/v1/stations/lab-upp-2/state"):  # fmt: skip
        refused = mine.get(url)
        assert refused.status_code == 404, url
        assert "no station named" in refused.text, url
    assert mine.get("/stations/lab-sto").status_code == 200
    assert mine.get("/stations/lab-shared").status_code == 200
    names = [s["name"] for s in everyone.get("/api/v1/stations").json()]
    assert names == ["lab-shared", "lab-sto", "lab-upp", "lab-upp-2"]  # archived too
    assert "site uppsala" in everyone.get("/stations").text


def test_a_station_of_a_site_seats_only_that_sites_participants(
    client: TestClient, database: Database, user_client: UserClientFactory
) -> None:
    """Seating another site's participant, or giving a station another site than its seated
    participant's, is refused with one line; a shared station seats anyone."""
    create_sites_study(database)
    admin = user_client(Role.ADMIN, "pi")
    everyone = user_client(Role.EXPERIMENTER, "both")
    _station(admin, client, "lab-upp", THEIRS)
    _station(admin, client, "lab-shared")
    ours, theirs = _enrol(everyone, MINE), _enrol(everyone, THEIRS)

    refused = everyone.put(
        "/api/v1/stations/lab-upp/participant", json={"study": "multi", "code": ours}
    )
    assert refused.status_code == 409
    assert refused.json()["detail"] == (
        "station 'lab-upp' belongs to site 'uppsala' and seats only its participants: "
        f"'{ours}' is enrolled at 'stockholm'"
    )
    on_console = everyone.post("/stations/lab-upp/assign", data={"study": "multi", "code": ours})
    assert "seats only its participants" in on_console.text
    seated = everyone.put(
        "/api/v1/stations/lab-upp/participant", json={"study": "multi", "code": theirs}
    )
    assert seated.status_code == 200 and seated.json()["site"] == THEIRS

    assert (
        everyone.put(
            "/api/v1/stations/lab-shared/participant", json={"study": "multi", "code": ours}
        ).status_code
        == 200
    )
    moved = admin.patch("/api/v1/stations/lab-shared", json={"site": THEIRS})
    assert moved.status_code == 409 and "seats only its participants" in moved.json()["detail"]
    assert admin.patch("/api/v1/stations/lab-shared", json={"site": MINE}).json()["site"] == MINE
    assert admin.patch("/api/v1/stations/lab-upp", json={"site": None}).json()["site"] is None
    with database.read_session() as db:
        changes = db.scalars(
            select(AuditEvent.details).where(AuditEvent.action == "station.site_set")
        ).all()
    assert changes == [{"from": None, "to": MINE}, {"from": THEIRS, "to": None}]
    assert everyone.patch("/api/v1/stations/lab-upp", json={"site": MINE}).status_code == 403


def test_a_station_site_is_one_a_study_declares(
    client: TestClient, database: Database, database_url: str, user_client: UserClientFactory
) -> None:
    """Created with a site (API, page form, command line) only if some study declares it: a typo
    would hide the station from every limited account."""
    create_sites_study(database)
    admin = user_client(Role.ADMIN, "pi")
    typo = admin.post("/api/v1/stations", json={"name": "lab-x", "site": "upsala"})
    assert typo.status_code == 422
    assert typo.json()["detail"] == (
        "site: no study declares site 'upsala' (sites declared: stockholm, uppsala)"
    )
    form = admin.get("/stations").text
    assert '<option value="uppsala">uppsala (multi)</option>' in form
    made = admin.post("/stations", data={"name": "lab-f", "site": THEIRS})
    assert made.status_code == 200 and "site uppsala" in made.text
    refused = admin.post("/stations", data={"name": "lab-g", "site": "upsala"})
    assert refused.status_code == 422 and "no study declares site" in refused.text
    code, out, _ = run(database_url, "station", "create", "lab-c", "--site", MINE)
    assert (code, out.strip()) == (0, "created station 'lab-c' of site 'stockholm'")
    code, _, err = run(database_url, "station", "create", "lab-d", "--site", "nowhere")
    assert code != 0 and "no study declares site 'nowhere'" in err
    code, out, _ = run(database_url, "station", "list")
    assert "lab-c                    stockholm        (free)" in out.splitlines()
    sites_of = {s["name"]: s["site"] for s in admin.get("/api/v1/stations").json()}
    assert sites_of == {"lab-c": MINE, "lab-f": THEIRS}


def test_a_shared_station_shows_a_limited_account_its_robots_contact_only_with_its_own_seated(
    client: TestClient, database: Database, user_client: UserClientFactory
) -> None:
    """Free, or seating a participant of a study without sites: no last contact, connection or
    notice (they would tell when another site last used it). With one of its own participants
    seated: what the robot did since they were seated, not before."""
    create_sites_study(database)
    admin = user_client(Role.ADMIN, "pi")
    everyone = user_client(Role.EXPERIMENTER, "both")
    _station(admin, client, "lab-shared")
    _station(admin, client, "lab-sto", MINE)
    mine = user_client(Role.EXPERIMENTER, "sto")
    limit(database, "sto", MINE)
    _heard(database, "lab-shared", minutes_ago=5)  # another site's session, say
    _heard(database, "lab-sto", minutes_ago=5)

    withheld = {"connected": None, "last_seen_at": None, "notice": None}
    assert {k: _devices(mine, "lab-shared")[0][k] for k in withheld} == withheld
    assert _devices(everyone, "lab-shared")[0]["notice"]["text"] == "battery low"
    assert _devices(mine, "lab-sto")[0]["last_seen_at"] is not None  # its site's own station
    page = mine.get("/stations").text
    assert page.count("not shown") == 1 and page.count(" UTC</td>") == 1
    console = mine.get("/stations/lab-shared").text
    assert "seat your participant to see" in console and "battery low" not in console

    ours = _enrol(everyone, MINE)
    assert (
        mine.put(
            "/api/v1/stations/lab-shared/participant", json={"study": "multi", "code": ours}
        ).status_code
        == 200
    )
    seated = _devices(mine, "lab-shared")[0]
    assert (seated["connected"], seated["last_seen_at"], seated["notice"]) == (False, None, None)
    _heard(database, "lab-shared", minutes_ago=-1)  # the robot, since they sat down
    seated = _devices(mine, "lab-shared")[0]
    assert seated["last_seen_at"] is not None and seated["notice"]["text"] == "battery low"
    assert "battery low" in mine.get("/stations/lab-shared").text


def test_a_robots_events_reach_those_who_may_see_its_contact(
    client: TestClient, database: Database, user_client: UserClientFactory
) -> None:
    """A robot connecting or posting a notice is news about when its station is used: its event
    names the station's site, else the seated participant's, else (a free shared station) no
    site, which only unlimited accounts hear."""
    create_sites_study(database)
    admin = user_client(Role.ADMIN, "pi")
    everyone = user_client(Role.EXPERIMENTER, "both")
    _station(admin, client, "lab-upp", THEIRS)
    _station(admin, client, "lab-shared")
    theirs = _enrol(everyone, THEIRS)

    def robot_event_site(station: str) -> object:
        """The site the event of the station's robot disconnecting names."""
        with database.writing() as db:
            device = db.scalar(select(Device).join(Station).where(Station.name == station))
            assert device is not None
            stations.socket_closed(db, device_id=device.id, socket_id="gone")
            (event,) = db.info[events.PENDING_KEY]
            db.rollback()
        assert event.type == stations.DEVICE_CONNECTION
        return event.data["site"]

    assert (robot_event_site("lab-shared"), robot_event_site("lab-upp")) == (None, THEIRS)
    everyone.put("/api/v1/stations/lab-shared/participant", json={"study": "multi", "code": theirs})
    assert robot_event_site("lab-shared") == THEIRS

    def heard_by(scope: sites.Scope, site: str | None) -> bool:
        return sites.reaches(
            scope, Event(topic="station:1", type="device_notice", data={"site": site})
        )

    stockholm = sites.Scope(frozenset({MINE}))
    assert not heard_by(stockholm, None) and not heard_by(stockholm, THEIRS)
    assert heard_by(stockholm, MINE) and heard_by(sites.Scope.every_site(), None)


def test_0023_gives_stations_a_site_shared_at_first(blank_database_url: str) -> None:
    """Upgrading leaves every existing station shared (NULL); the downgrade drops the column."""
    database = Database(blank_database_url)
    schema.upgrade(database, "0022")
    with database.engine.begin() as connection:
        _insert_row(connection, "station", id=1, name="a")
    schema.upgrade(database, "0023")
    with database.engine.connect() as connection:
        assert connection.execute(text("SELECT site FROM station")).all() == [(None,)]
    schema.downgrade(database, "0022")
    with database.engine.connect() as connection:
        columns = connection.execute(text("SELECT * FROM station")).keys()
    assert "site" not in columns
    database.dispose()
