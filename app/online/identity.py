"""Who an online participant is, kept as little as possible: keyed hashes and derived keys.

A recruitment ID (Prolific's PROLIFIC_PID, MTurk's workerId) is personal data: it links the study's
data to a person's account on the platform. It is stored only as ``HMAC(server key, study:ID)``,
which finds the participation again when the same ID comes back and lets an admin who types an
ID find its participant, but from which nobody without the server's key can tell the ID
(docs/data-protection.md). The browser's own random id (a cookie) is hashed the same way.

The virtual station's device key is derived from the participation, as the tablet's links are
(app.services.participants.tablet_tokens): the database keeps its SHA-256, and a participant who
reloads the page gets the same key again without it ever being stored.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import re

from app.errors import InvalidInput
from app.i18n.catalogues import Message
from app.services.sessions.stations import KEY_PREFIX

RECRUITMENT_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.:@-]{0,127}")
"""What a platform's participant ID looks like (Prolific: 24 hex digits; MTurk: A1B2…)."""
BROWSER_ID = re.compile(r"[A-Za-z0-9_-]{16,64}")


def _mac(secret: bytes, purpose: str, *parts: object) -> bytes:
    message = ":".join([purpose, *map(str, parts)]).encode()
    return hmac.new(secret, message, hashlib.sha256).digest()


def check_recruitment_id(value: str, *, parameter: str) -> str:
    """The ID as given, or InvalidInput naming the parameter and the rule."""
    value = value.strip()
    if not RECRUITMENT_ID.fullmatch(value):
        raise InvalidInput(
            Message(
                "the link's %(parameter)s is missing or malformed: open the study again from "
                "the recruitment platform",
                parameter=parameter,
            )
        )
    return value


def recruitment_hash(secret: bytes, study_id: int, recruitment_id: str) -> str:
    """The stored form of a recruitment ID in one study (hex, 64 characters)."""
    return _mac(secret, "recruitment", study_id, recruitment_id).hex()


def browser_hash(secret: bytes, browser_id: str) -> str:
    """The stored form of a browser's own random id ('' for none or a malformed one)."""
    if not BROWSER_ID.fullmatch(browser_id):
        return ""
    return _mac(secret, "browser", browser_id).hex()


def device_key(secret: bytes, participation_id: int, generation: int) -> str:
    """The key of an online participation's virtual station (a station API key, ``tlk_…``)."""
    mac = _mac(secret, "online-device", participation_id, generation)
    return KEY_PREFIX + base64.urlsafe_b64encode(mac[:30]).decode().rstrip("=")
