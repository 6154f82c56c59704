"""A small running study that access and fuzz tests share: users of every role, two participants
(P001 at station lab-1, P002 at lab-2) past their pre-study questionnaires with a session started
and one open step each, a robot key per station, tablet tokens and a kiosk token for lab-1."""

from __future__ import annotations

from dataclasses import dataclass, field

from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.access import Principal
from app.db import Database
from app.services.audit import Actor
from app.services.participants import enrolment, tablet_tokens
from app.services.sessions import runtime, stations
from app.tables import Role
from app.tablet import TABLET_COOKIE
from tests.conftest import give_pre_study, make_user, sign_in_api

SYSTEM = Actor.system("policy")


@dataclass
class World:
    """The study, participants, stations, keys and tokens every probe refers to."""

    app: FastAPI
    secret: bytes
    tokens: dict[str, str] = field(default_factory=dict)  # participant code → tablet token
    keys: dict[str, str] = field(default_factory=dict)  # station → device key
    kiosk: str = ""
    step: int = 0  # an open step at lab-1 (P001's)


def build_world(app: FastAPI, database: Database, exp3_study: str) -> World:
    """Two participants at two stations, each with a tablet token, a robot key and an open step."""
    found = World(app, app.state.settings.secret)
    for role in Role:
        make_user(database, role.value, role)
    make_user(database, "throwaway", Role.ANALYST)
    for code, station in (("P001", "lab-1"), ("P002", "lab-2")):
        with database.writing() as db:
            participant = enrolment.enroll_participant(
                db, study_name=exp3_study, actor=SYSTEM, code=code
            ).participant
        with database.writing() as db:
            participant = db.merge(participant)
            found.tokens[code] = tablet_tokens.issue_participant_token(
                db, participant=participant, secret=found.secret, actor=SYSTEM
            )
        participant = give_pre_study(
            database, study=exp3_study, participant=participant, actor=SYSTEM
        )
        with database.writing() as db:
            stations.create_station(db, name=station, actor=SYSTEM)
        with database.writing() as db:
            found.keys[station] = stations.issue_device_key(
                db, station_name=station, label="robot", actor=SYSTEM
            ).key
        with database.writing() as db:
            stations.assign_participant(
                db, station_name=station, participant=db.merge(participant), actor=SYSTEM
            )
        with database.writing() as db:
            runtime.start_session(db, station_name=station, actor=SYSTEM)
        with database.writing() as db:
            step = runtime.request_prompt(
                db, station_name=station, category="conation", actor=SYSTEM
            )
            if station == "lab-1":
                found.step = step.prompt.id
    with database.writing() as db:
        found.kiosk = tablet_tokens.issue_kiosk_token(
            db, station=stations.get_station(db, "lab-1"), secret=found.secret, actor=SYSTEM
        )
    return found


def client_for(world: World, principal: Principal) -> TestClient:
    """A fresh client holding exactly this principal's credentials."""
    client = TestClient(world.app)
    if principal in (Principal.PARTICIPANT_OWN, Principal.PARTICIPANT_OTHER):
        token = world.tokens["P001" if principal is Principal.PARTICIPANT_OWN else "P002"]
        client.headers["Authorization"] = f"Bearer {token}"
        client.cookies.set(TABLET_COOKIE, token)
    elif principal in (Principal.DEVICE_OWN, Principal.DEVICE_OTHER):
        station = "lab-1" if principal is Principal.DEVICE_OWN else "lab-2"
        client.headers["Authorization"] = f"Bearer {world.keys[station]}"
    elif principal in (Principal.EXPERIMENTER, Principal.ANALYST, Principal.ADMIN):
        sign_in_api(client, principal.value)
    return client
