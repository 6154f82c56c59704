"""Stations for experimenters: assignment, session control, devices, and Wizard-of-Oz steps.

The Wizard-of-Oz routes (prompts and answers by an experimenter when no robot client is used) go
through exactly the same operations as the robot's own routes (app/api/station_ops.py).
"""

from __future__ import annotations

from collections import defaultdict

from fastapi import Depends, Request, Response, status
from sqlalchemy import select

from app.api import station_ops
from app.api.runtime_schemas import (
    AnswerRequest,
    Assignment,
    DeviceCreate,
    DeviceOut,
    IssuedDeviceOut,
    PromptRequest,
    StaffAnswerOut,
    StaffPromptOut,
    StaffStationStateOut,
    StationCreate,
    StationOut,
    StationUpdate,
    StepIdPath,
)
from app.api.schemas import TabletLink
from app.api.station_ops import device_out
from app.deps import (
    AdminUser,
    ExperimenterUser,
    OneHopRouter,
    SessionDep,
    SettingsDep,
    station_in_scope,
)
from app.inputs import RowId
from app.services import studies
from app.services.audit import Actor
from app.services.participants import enrolment, tablet_tokens
from app.services.privacy import sites
from app.services.sessions import runtime, stations
from app.tables import Device, Participant, Station, Study, User

router = OneHopRouter(
    prefix="/stations", tags=["stations"], dependencies=[Depends(station_in_scope)]
)
devices_router = OneHopRouter(prefix="/devices", tags=["stations"])


def _stations_out(db: SessionDep, found: list[Station], actor: Actor) -> list[StationOut]:
    """Stations with who is seated there and their devices, as much of their robots' contact as
    ``actor`` may see (app.services.privacy.sites.Contact): two queries, however many."""
    ids = [station.id for station in found]
    seated = {
        station_id: (code, study, site)
        for station_id, code, study, site in db.execute(
            select(Station.id, Participant.code, Study.name, Participant.site)
            .join(Participant, Participant.id == Station.participant_id)
            .join(Study, Study.id == Participant.study_id)
            .where(Station.id.in_(ids))
        )
    }
    devices: dict[int, list[Device]] = defaultdict(list)
    for device in db.scalars(select(Device).where(Device.station_id.in_(ids)).order_by(Device.id)):
        devices[device.station_id].append(device)
    out = []
    for station in found:
        code, study, site = seated.get(station.id, (None, None, None))
        contact = sites.contact(station, site, actor)
        out.append(
            StationOut(
                name=station.name,
                site=station.site,
                participant=code,
                study=study,
                devices=[device_out(d, station, contact) for d in devices[station.id]],
            )
        )
    return out


def _station_out(db: SessionDep, station_name: str, user: User) -> StationOut:
    station = stations.get_station(db, station_name)
    return _stations_out(db, [station], Actor.of_user(user))[0]


@router.get("")
def list_stations(db: SessionDep, user: ExperimenterUser) -> list[StationOut]:
    """Every station the account may see (an account limited to some sites: those of its sites
    and the shared ones), who is assigned and its devices."""
    actor = Actor.of_user(user)
    return _stations_out(db, sites.visible_stations(db, stations.list_stations(db), actor), actor)


@router.post("", status_code=status.HTTP_201_CREATED)
def create_station(body: StationCreate, db: SessionDep, admin: AdminUser) -> StationOut:
    """Create a station (admin), of a site or shared."""
    station = stations.create_station(
        db, name=body.name, site=body.site, actor=Actor.of_user(admin)
    )
    return _station_out(db, station.name, admin)


@router.patch("/{name}")
def update_station(name: str, body: StationUpdate, db: SessionDep, admin: AdminUser) -> StationOut:
    """Give the station a site, or make it shared (``site`` null) (admin)."""
    stations.set_station_site(db, station_name=name, site=body.site, actor=Actor.of_user(admin))
    return _station_out(db, name, admin)


@router.get("/{name}/state")
def get_state(name: str, db: SessionDep, user: ExperimenterUser) -> StaffStationStateOut:
    """The station's live state, as its robot sees it (without the learners' figures while the
    seated participant's study is blinded)."""
    return station_ops.staff_state(runtime.station_view(db, station_name=name))


@router.put("/{name}/participant")
def assign(name: str, body: Assignment, db: SessionDep, user: ExperimenterUser) -> StationOut:
    """Seat a participant at the station. A station that runs no study yet runs this one from
    now on, as on the console (its room client then keeps the study's room between
    participants)."""
    study = studies.get_study(db, body.study)
    participant = enrolment.get_participant(db, study, body.code, actor=Actor.of_user(user))
    stations.assign_participant(
        db,
        station_name=name,
        participant=participant,
        actor=Actor.of_user(user),
        tie_untied_to=study,
    )
    return _station_out(db, name, user)


@router.delete("/{name}/participant")
def unassign(name: str, db: SessionDep, user: ExperimenterUser) -> StationOut:
    """Free the station (refused while a session runs)."""
    stations.unassign(db, station_name=name, actor=Actor.of_user(user))
    return _station_out(db, name, user)


@router.post("/{name}/sessions", status_code=status.HTTP_201_CREATED)
def start_session(name: str, db: SessionDep, user: ExperimenterUser) -> StaffStationStateOut:
    """Start the assigned participant's next session and its first run."""
    return station_ops.staff_state(
        runtime.start_session(db, station_name=name, actor=Actor.of_user(user))
    )


@router.post("/{name}/sessions/current/end")
def end_session(name: str, db: SessionDep, user: ExperimenterUser) -> StaffStationStateOut:
    """End the running session early."""
    return station_ops.staff_state(
        runtime.end_session(db, station_name=name, actor=Actor.of_user(user))
    )


@router.post("/{name}/runs", status_code=status.HTTP_201_CREATED)
def start_run(name: str, db: SessionDep, user: ExperimenterUser) -> StaffStationStateOut:
    """Start the next run of the running session."""
    return station_ops.staff_state(
        runtime.start_run(db, station_name=name, actor=Actor.of_user(user))
    )


@router.post("/{name}/runs/current/end")
def end_run(name: str, db: SessionDep, user: ExperimenterUser) -> StaffStationStateOut:
    """End the running run early (its unanswered categories stay unanswered)."""
    return station_ops.staff_state(
        runtime.end_run(db, station_name=name, actor=Actor.of_user(user))
    )


@router.post(
    "/{name}/prompts",
    status_code=status.HTTP_201_CREATED,
    responses={200: {"description": "The category's open prompt, handed out again."}},
)
def prompt(
    name: str, body: PromptRequest, db: SessionDep, user: ExperimenterUser, response: Response
) -> StaffPromptOut:
    """Wizard-of-Oz: trigger a category as the robot would."""
    out = station_ops.wizard_prompt(db, station=name, body=body, actor=Actor.of_user(user))
    if not out.created:
        response.status_code = status.HTTP_200_OK
    return out


@router.post("/{name}/steps/{step_id}/answer")
def answer(
    name: str, step_id: StepIdPath, body: AnswerRequest, db: SessionDep, user: ExperimenterUser
) -> StaffAnswerOut:
    """Wizard-of-Oz: record the participant's yes/no answer as the robot would."""
    return station_ops.wizard_answer(
        db, station=name, step_id=step_id, body=body, actor=Actor.of_user(user)
    )


@router.post("/{name}/devices", status_code=status.HTTP_201_CREATED)
def issue_key(name: str, body: DeviceCreate, db: SessionDep, admin: AdminUser) -> IssuedDeviceOut:
    """Create a device key for the station (admin); the key is shown only in this response."""
    issued = stations.issue_device_key(
        db, station_name=name, label=body.label, actor=Actor.of_user(admin)
    )
    # an admin's route, and admins see every site: all of the contact
    public = device_out(issued.device, issued.device.station, sites.Contact())
    return IssuedDeviceOut(**public.model_dump(), key=issued.key)


@devices_router.post("/{device_id}/revoke")
def revoke_key(device_id: RowId, db: SessionDep, admin: AdminUser) -> DeviceOut:
    """Revoke a device key at once (admin)."""
    device = stations.revoke_device(db, device_id=device_id, actor=Actor.of_user(admin))
    return device_out(device, device.station, sites.Contact())  # an admin's, as above


@router.post("/{name}/kiosk")
def issue_kiosk(
    name: str, request: Request, db: SessionDep, settings: SettingsDep, admin: AdminUser
) -> TabletLink:
    """Issue (or reissue) the station's kiosk link: a tablet that shows whoever is seated here."""
    station = stations.get_station(db, name, for_update=True)
    token = tablet_tokens.issue_kiosk_token(
        db, station=station, secret=settings.secret, actor=Actor.of_user(admin)
    )
    return TabletLink(token=token, url=f"{str(request.base_url).rstrip('/')}/k/{token}")
