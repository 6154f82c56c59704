"""The escape room in the browser: the page a lab machine or a headset opens for a station.

The page is a shell that anyone may load: what it can do comes from the station's device key,
typed into it once and kept by that browser (revoking the key closes the room). From there on it
is an ordinary robot client: static/js/room.js speaks the public robot API (the station
WebSocket, ``GET /api/v1/station/room``) and nothing else, exactly as a Unity or Pepper client
would (docs/escape-room.md).
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response

from app.errors import NotFound
from app.inputs import STATION_NAME
from app.web.templating import render

router = APIRouter(tags=["pages"], include_in_schema=False)

ROOM_PERMISSIONS = "camera=(), microphone=(self), geolocation=(), xr-spatial-tracking=(self)"
"""The room may ask for the microphone (speech answers) and a headset's tracking (WebXR): the
other pages forbid both (app.http.SECURITY_HEADERS)."""


@router.get("/stations/{name}/room")
def room_page(request: Request, name: str) -> Response:
    """The room client of station ``name`` (it asks for the station's device key once)."""
    if not STATION_NAME.matches(name):
        raise NotFound(f"no station named {name!r}: {STATION_NAME.rule}")
    response = render(request, "room.html", {"station": name})
    response.headers["permissions-policy"] = ROOM_PERMISSIONS
    return response
