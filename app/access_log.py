"""The server's access log without participant codes: how ``trustlab serve`` configures uvicorn's.

Staff pages and the API name participants in their paths (``/studies/S/participants/P017/…``),
and tablet and kiosk links carry their token (``/t/TOKEN``, ``/k/TOKEN``): uvicorn's access log,
one line per request, would keep every code and link for as long as the lab keeps its logs, out of
reach of erasure. ``TRUSTLAB_ACCESS_LOG`` (app.settings) chooses:

- ``redacted`` (the default): each request is logged with those path segments, and ``code`` or
  ``token`` query values, replaced by ``[hidden]``;
- ``off``: no access log (errors are still logged);
- ``full``: the paths as requested (for debugging a lab's setup; the codes are then in the log).
"""

from __future__ import annotations

import copy
import logging
import re
from enum import StrEnum
from typing import Any

HIDDEN = "[hidden]"
_SEGMENT = re.compile(r"(/participants/|/t/|/k/)[^/?#]+")
_QUERY = re.compile(r"([?&](?:code|token)=)[^&#]*")


class AccessLog(StrEnum):
    """What the server's access log shows (``TRUSTLAB_ACCESS_LOG``)."""

    REDACTED = "redacted"
    OFF = "off"
    FULL = "full"


def redact(path: str) -> str:
    """The request path (with its query) as the access log may show it: no code, no token."""
    return _QUERY.sub(rf"\g<1>{HIDDEN}", _SEGMENT.sub(rf"\g<1>{HIDDEN}", path))


class RedactingFilter(logging.Filter):
    """On uvicorn's access logger: every path among a record's arguments redacted (HTTP lines
    carry it third, WebSocket lines second)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(
                redact(arg) if isinstance(arg, str) and arg.startswith("/") else arg
                for arg in record.args
            )
        return True


def log_config(mode: AccessLog) -> dict[str, Any]:
    """uvicorn's logging configuration for ``mode`` (its own, plus the redacting filter)."""
    from uvicorn.config import LOGGING_CONFIG  # only `trustlab serve` needs uvicorn loaded

    config = copy.deepcopy(LOGGING_CONFIG)
    if mode == AccessLog.REDACTED:
        config["filters"] = {"redact_codes": {"()": RedactingFilter}}
        config["handlers"]["access"]["filters"] = ["redact_codes"]
    return config
