"""Who may call what: the access policy of every route, as data.

Each route (method, path) lists the principals allowed to use it; everyone else is refused (401
without credentials of the right kind, 403 for a role that lacks the right, 404 for a robot
asking about another station's step). ``tests/app/test_access_policy.py`` enumerates the app's
routes, fails if one has no entry here, and exercises every cell of this table.

Principals:

- ``anonymous``: no credentials;
- ``participant`` (own / other): a tablet token; *own* when the route's resource belongs to that
  participant, *other* when it belongs to someone else (tablet routes act on the token's own
  participant, so both are allowed there);
- ``device`` (own / other station): a robot's key; *own* when the route's resource belongs to the
  key's station;
- ``experimenter``, ``analyst``, ``admin``: a signed-in person of that role.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import StrEnum


class Principal(StrEnum):
    """A kind of caller."""

    ANONYMOUS = "anonymous"
    PARTICIPANT_OWN = "participant-own"
    PARTICIPANT_OTHER = "participant-other"
    DEVICE_OWN = "device-own"
    DEVICE_OTHER = "device-other"
    EXPERIMENTER = "experimenter"
    ANALYST = "analyst"
    ADMIN = "admin"


P = Principal
EVERYONE = frozenset(Principal)
USERS = frozenset({P.EXPERIMENTER, P.ANALYST, P.ADMIN})
STAFF = frozenset({P.EXPERIMENTER, P.ADMIN})
ANALYSTS = frozenset({P.ANALYST, P.ADMIN})
ADMINS = frozenset({P.ADMIN})
PARTICIPANTS = frozenset({P.PARTICIPANT_OWN, P.PARTICIPANT_OTHER})
DEVICES = frozenset({P.DEVICE_OWN, P.DEVICE_OTHER})
OWN_DEVICE = frozenset({P.DEVICE_OWN})
NOBODY_ELSE: frozenset[Principal] = frozenset()
"""A route only its own kind of caller reaches (an online participant's cookie)."""

POLICY: Mapping[tuple[str, str], frozenset[Principal]] = {
    # public: health, API description, sign-in, static files, tablet links (the token is the key)
    ("GET", "/healthz"): EVERYONE,
    ("GET", "/api/v1/ping"): EVERYONE,
    ("GET", "/api/v1/openapi.json"): EVERYONE,
    ("GET", "/api/v1/docs"): EVERYONE,
    ("GET", "/static"): EVERYONE,
    ("GET", "/favicon.ico"): EVERYONE,
    ("GET", "/login"): EVERYONE,
    ("POST", "/login"): EVERYONE,
    ("POST", "/api/v1/session"): EVERYONE,
    ("GET", "/t/{token}"): EVERYONE,
    ("GET", "/k/{token}"): EVERYONE,
    ("GET", "/stations/{name}/room"): EVERYONE,  # a shell: the device key typed into it is the key
    ("GET", "/tablet/left"): EVERYONE,  # an erased participant's thank-you page: names nobody
    ("GET", "/api/v1/languages/{language}/words"): EVERYONE,  # interface sentences only
    # an online study's public link (app.online.pages): the platform's ID is the key
    ("GET", "/join/{study}"): EVERYONE,
    ("POST", "/join/{study}"): EVERYONE,
    # an online participant's own pages: only the cookie their join set opens them, which none
    # of the principals here holds (tests/app/test_online_pages.py tries them with it)
    ("GET", "/online"): NOBODY_ELSE,
    ("POST", "/online/start"): NOBODY_ELSE,
    ("POST", "/online/away"): NOBODY_ELSE,
    # signed-in people
    ("POST", "/logout"): USERS,
    ("GET", "/api/v1/session"): USERS,
    ("DELETE", "/api/v1/session"): USERS,
    ("GET", "/account"): USERS,
    ("POST", "/account/password"): USERS,
    ("GET", "/"): USERS,
    ("GET", "/api/v1/studies"): USERS,
    ("GET", "/api/v1/studies/{name}"): USERS,
    ("GET", "/api/v1/studies/{name}/protocol"): USERS,
    ("GET", "/api/v1/studies/{name}/participants"): USERS,
    ("GET", "/api/v1/studies/{name}/participants/{code}"): USERS,
    ("GET", "/studies/{name}"): USERS,
    ("GET", "/studies/{name}/dashboard"): USERS,
    ("GET", "/studies/{name}/monitor"): USERS,
    ("GET", "/api/v1/protocols"): USERS,
    ("GET", "/admin/protocols/edit"): ADMINS,
    ("POST", "/admin/protocols/edit"): ADMINS,
    ("POST", "/admin/protocols/check"): ADMINS,
    ("GET", "/studies/{name}/preview"): USERS,
    ("GET", "/studies/{name}/preview/room/{language}"): USERS,
    ("GET", "/studies/{name}/preview/room/{language}/api/room"): USERS,
    ("GET", "/studies/{name}/preview/room/{language}/api/speech"): USERS,
    ("GET", "/studies/{name}/preview/room/{language}/api/speech/audio"): USERS,
    ("WS", "/studies/{name}/preview/room/{language}/api/ws"): USERS,
    ("GET", "/studies/{name}/protocol.toml"): ANALYSTS,
    ("GET", "/studies/{name}/preview/{language}/{number}"): USERS,
    ("POST", "/studies/{name}/preview/{language}/{number}"): USERS,
    ("GET", "/studies/{name}/dashboard.json"): USERS,
    ("GET", "/studies/{name}/events"): USERS,
    ("GET", "/studies/{name}/participants/{code}"): USERS,
    ("GET", "/stations/{name}/events"): USERS,
    # experimenters (and admins): enrolment, participants, sessions, Wizard-of-Oz
    ("POST", "/api/v1/studies/{name}/participants"): STAFF,
    ("POST", "/api/v1/studies/{name}/participants/{code}/withdraw"): STAFF,
    ("POST", "/api/v1/studies/{name}/participants/{code}/erase"): STAFF,
    ("GET", "/api/v1/studies/{name}/participants/{code}/link"): STAFF,
    ("POST", "/api/v1/studies/{name}/participants/{code}/link"): STAFF,
    ("DELETE", "/api/v1/studies/{name}/participants/{code}/link"): STAFF,
    ("POST", "/api/v1/studies/{name}/participants/{code}/lock"): STAFF,
    ("POST", "/api/v1/studies/{name}/participants/{code}/unlock"): STAFF,
    ("POST", "/studies/{name}/participants"): STAFF,
    ("GET", "/studies/{name}/participants/{code}/withdraw"): STAFF,
    ("POST", "/studies/{name}/participants/{code}/withdraw"): STAFF,
    ("POST", "/studies/{name}/participants/{code}/link"): STAFF,
    ("POST", "/studies/{name}/participants/{code}/link/revoke"): STAFF,
    ("POST", "/studies/{name}/participants/{code}/lock"): STAFF,
    ("POST", "/studies/{name}/participants/{code}/language"): STAFF,
    ("POST", "/studies/{name}/participants/{code}/unlock"): STAFF,
    ("GET", "/api/v1/stations"): STAFF,
    ("GET", "/api/v1/stations/{name}/state"): STAFF,
    ("PUT", "/api/v1/stations/{name}/participant"): STAFF,
    ("DELETE", "/api/v1/stations/{name}/participant"): STAFF,
    ("POST", "/api/v1/stations/{name}/sessions"): STAFF,
    ("POST", "/api/v1/stations/{name}/sessions/current/end"): STAFF,
    ("POST", "/api/v1/stations/{name}/runs"): STAFF,
    ("POST", "/api/v1/stations/{name}/runs/current/end"): STAFF,
    ("POST", "/api/v1/stations/{name}/prompts"): STAFF,
    ("POST", "/api/v1/stations/{name}/steps/{step_id}/answer"): STAFF,
    ("GET", "/stations"): STAFF,
    ("GET", "/stations/{name}"): STAFF,
    ("GET", "/stations/{name}/room-panel"): STAFF,
    ("POST", "/stations/{name}/assign"): STAFF,
    ("POST", "/stations/{name}/study"): STAFF,
    ("POST", "/stations/{name}/unassign"): STAFF,
    ("POST", "/stations/{name}/session/start"): STAFF,
    ("POST", "/stations/{name}/session/end"): STAFF,
    ("POST", "/stations/{name}/run/start"): STAFF,
    ("POST", "/stations/{name}/run/end"): STAFF,
    ("POST", "/stations/{name}/woz/prompt"): STAFF,
    ("POST", "/stations/{name}/woz/answer"): STAFF,
    # analysts (and admins): analysis and exports
    ("GET", "/studies/{name}/analysis"): ANALYSTS,
    ("GET", "/studies/{name}/analysis/mixed"): ANALYSTS,
    ("GET", "/studies/{name}/analysis/power"): ANALYSTS,
    ("GET", "/studies/{name}/exports/{export}"): ANALYSTS,
    # admins: accounts, studies, stations and keys, the audit log
    ("POST", "/api/v1/studies"): ADMINS,
    ("POST", "/api/v1/studies/{name}/status"): ADMINS,
    ("POST", "/api/v1/studies/{name}/unblind"): ADMINS,
    ("POST", "/api/v1/studies/{name}/phase"): ADMINS,
    ("POST", "/api/v1/studies/{name}/pilot/reset"): ADMINS,
    ("POST", "/api/v1/stations"): ADMINS,
    ("PATCH", "/api/v1/stations/{name}"): ADMINS,
    ("POST", "/api/v1/stations/{name}/devices"): ADMINS,
    ("POST", "/api/v1/stations/{name}/kiosk"): ADMINS,
    ("POST", "/api/v1/devices/{device_id}/revoke"): ADMINS,
    ("GET", "/admin/users"): ADMINS,
    ("POST", "/admin/users"): ADMINS,
    ("GET", "/admin/users/{username}"): ADMINS,
    ("GET", "/admin/users/{username}/disable"): ADMINS,
    ("POST", "/admin/users/{username}/disable"): ADMINS,
    ("GET", "/admin/users/{username}/password"): ADMINS,
    ("POST", "/admin/users/{username}/enable"): ADMINS,
    ("POST", "/admin/users/{username}/role"): ADMINS,
    ("POST", "/admin/users/{username}/password"): ADMINS,
    ("POST", "/admin/users/{username}/unlock"): ADMINS,
    ("POST", "/admin/users/{username}/sites"): ADMINS,
    ("GET", "/admin/studies/new"): ADMINS,
    ("POST", "/admin/studies"): ADMINS,
    ("POST", "/admin/studies/{name}/status"): ADMINS,
    ("POST", "/admin/studies/{name}/archive"): ADMINS,
    ("GET", "/admin/studies/{name}/unblind"): ADMINS,
    ("POST", "/admin/studies/{name}/unblind"): ADMINS,
    ("GET", "/admin/studies/{name}/protocol"): ADMINS,
    ("POST", "/admin/studies/{name}/protocol"): ADMINS,
    ("POST", "/admin/studies/{name}/protocol/undo"): ADMINS,
    ("POST", "/admin/studies/{name}/protocol/check"): ADMINS,
    ("POST", "/admin/studies/{name}/split"): ADMINS,
    ("GET", "/admin/studies/{name}/design/{slug}"): ADMINS,
    ("POST", "/admin/studies/{name}/design/{slug}"): ADMINS,
    ("POST", "/admin/studies/{name}/design/{slug}/check"): ADMINS,
    ("GET", "/admin/studies/{name}/phase"): ADMINS,
    ("POST", "/admin/studies/{name}/phase"): ADMINS,
    ("GET", "/admin/studies/{name}/pilot/reset"): ADMINS,
    ("POST", "/admin/studies/{name}/pilot/reset"): ADMINS,
    ("POST", "/admin/studies/{name}/consent"): ADMINS,
    ("GET", "/admin/audit"): ADMINS,
    ("GET", "/admin/audit.csv"): ADMINS,
    ("POST", "/stations"): ADMINS,
    ("POST", "/stations/{name}/devices"): ADMINS,
    ("GET", "/stations/{name}/devices/{device_id}"): ADMINS,
    ("POST", "/stations/{name}/kiosk"): ADMINS,
    ("POST", "/stations/{name}/archive"): ADMINS,
    ("POST", "/devices/{device_id}/revoke"): ADMINS,
    # robots: their own station only
    ("GET", "/api/v1/station"): DEVICES,
    ("GET", "/api/v1/station/room"): DEVICES,
    ("PUT", "/api/v1/station/presence"): DEVICES,
    ("GET", "/api/v1/station/speech"): DEVICES,
    ("PUT", "/api/v1/station/notice"): DEVICES,
    ("POST", "/api/v1/station/prompts"): DEVICES,
    ("POST", "/api/v1/station/runs"): DEVICES,
    ("POST", "/api/v1/station/steps/{step_id}/answer"): OWN_DEVICE,
    ("WS", "/api/v1/station/ws"): DEVICES,
    ("WS", "/api/v1/station/audio"): DEVICES,
    ("GET", "/api/v1/station/speech/audio"): DEVICES,
    # the participant's tablet (each token reaches its own participant's pages only)
    ("GET", "/api/v1/tablet"): PARTICIPANTS,
    ("POST", "/api/v1/tablet/consent"): PARTICIPANTS,
    ("POST", "/api/v1/tablet/language"): PARTICIPANTS,
    ("POST", "/api/v1/tablet/questionnaires/{instrument}"): PARTICIPANTS,
    ("GET", "/tablet"): PARTICIPANTS,
    ("GET", "/tablet/language"): PARTICIPANTS,
    ("POST", "/tablet/language"): PARTICIPANTS,
    ("GET", "/tablet/consent"): PARTICIPANTS,
    ("POST", "/tablet/consent"): PARTICIPANTS,
    ("GET", "/tablet/q/{instrument}"): PARTICIPANTS,
    ("POST", "/tablet/q/{instrument}"): PARTICIPANTS,
    ("GET", "/tablet/q/{instrument}/{session}"): PARTICIPANTS,
    ("POST", "/tablet/q/{instrument}/{session}"): PARTICIPANTS,
    ("GET", "/tablet/wait"): PARTICIPANTS,
    ("GET", "/tablet/done"): PARTICIPANTS,
    ("GET", "/tablet/withdrawn"): PARTICIPANTS,
    ("GET", "/tablet/events"): PARTICIPANTS,
}
