"""The one settings object: every knob read from the environment (or ``.env``) lives here.

Nothing else in trustlab reads ``os.environ``; code that needs configuration receives a
:class:`Settings` (the web app keeps one on ``app.state``, the CLI builds one per command).
"""

from __future__ import annotations

import ipaddress
import os
import secrets
from functools import cached_property
from pathlib import Path
from typing import Annotated

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from app.access_log import AccessLog

REPO_ROOT = Path(__file__).resolve().parent.parent
"""The checkout (or image) root: migrations/, templates/ and static/ live beside the packages."""
KEEP_ALIVE_SECONDS = 75
"""How long the server keeps an idle HTTP connection open (nginx's default). uvicorn's own 5 s is
shorter than a participant's pause between two pages: each next page then opened a connection,
and a request sent just as the server closed its idle one failed (bench/online.py's
``ReadError``s)."""


class Settings(BaseSettings):
    """Deployment configuration, from ``TRUSTLAB_*`` environment variables or ``.env``."""

    model_config = SettingsConfigDict(
        env_prefix="TRUSTLAB_", env_file=".env", extra="ignore", frozen=True
    )

    database_url: str = Field(
        default="sqlite:///var/trustlab.sqlite3",
        description="SQLAlchemy URL; SQLite (default) or postgresql+psycopg://user@host/db.",
    )
    var_dir: Path = Field(
        default=Path("var"),
        description="Where the default SQLite file, the generated secret key and backups live.",
    )
    secret_key: SecretStr | None = Field(
        default=None,
        description=(
            "Signs the sign-in form's and the tablet forms' CSRF tokens and the one-time notice "
            "cookie, and derives the tablet and kiosk links (after a change, issued links still "
            "work but cannot be shown again until reissued); sign-in sessions do not use it. "
            "Generated once into var/secret_key when not given."
        ),
    )
    pseudonym_key: SecretStr | None = Field(
        default=None,
        description=(
            "The key of pseudonymised exports (`trustlab export --pseudonymise`, the analysis "
            "page's pseudonymised downloads): participant codes become keyed hashes that cannot "
            "be linked back without it. Keep it on the server, apart from the files shared."
        ),
    )
    checkpoint_dir: Path | None = Field(
        default=None,
        description="Pre-trained meta-policy checkpoints; defaults to the ones shipped in models/.",
    )
    admin_username: str = Field(default="admin", description="The account `trustlab init` creates.")
    admin_password: SecretStr | None = Field(
        default=None,
        description="Its password; if unset, a random one is generated and printed once.",
    )
    session_hours: float = Field(
        default=12.0, gt=0, description="An experimenter login expires this long after sign-in."
    )
    idle_minutes: float = Field(
        default=120.0, gt=0, description="A login left unused this long expires early."
    )
    cookie_secure: bool | None = Field(
        default=None,
        description="Force the Secure cookie flag; by default it follows the request's scheme.",
    )
    sqlite_synchronous: str = Field(
        default="FULL",
        description="PRAGMA synchronous for SQLite: FULL survives power loss, NORMAL only crashes.",
    )
    freeze_heap_at_start: bool = Field(
        default=True,
        description=(
            "Once the server has started, move every object then alive out of the garbage "
            "collector's full collections, which would otherwise pause requests "
            "(app/collector.py). Off only where one process starts and stops many applications, "
            "as the tests do: each start's collection walks the whole heap (about 0.3 s with the "
            "models loaded)."
        ),
    )
    analysis_processes: int = Field(
        default=2,
        ge=0,
        le=64,
        description=(
            "Worker processes per server process that fit the analyses (mixed models, ANOVAs) in "
            "the background, at a lower priority than the server; 0 fits them in a thread of "
            "the server instead, which slows its other requests while it runs "
            "(app/services/analysis_views/fit_runner.py)."
        ),
    )
    analysis_wait_seconds: float = Field(
        default=1.0,
        ge=0,
        description=(
            'How long an analysis page waits for a fit before it shows "fitting… started N s '
            'ago" and fills in when the fit is done.'
        ),
    )
    websocket_heartbeat_seconds: float = Field(
        default=15.0, gt=0, description="How often robot WebSockets are pinged."
    )
    websocket_auth_seconds: float = Field(
        default=10.0,
        gt=0,
        description="How long a robot WebSocket without a key header has to send its auth message.",
    )
    host: str = Field(default="127.0.0.1", description="Where `trustlab serve` listens.")
    port: int = Field(default=8000, ge=1, le=65535, description="The port `trustlab serve` uses.")
    shutdown_grace_seconds: int = Field(
        default=5,
        ge=1,
        le=300,
        description=(
            "How long `trustlab serve` waits, when told to stop, for requests still running: an "
            "answer takes milliseconds, but the consoles' and tablets' live streams never end by "
            "themselves, so they are cut after this (the pages reconnect to the next server)."
        ),
    )
    access_log: AccessLog = Field(
        default=AccessLog.REDACTED,
        description=(
            "What `trustlab serve`'s access log shows of each request: `redacted` (participant "
            "codes in paths and tablet or kiosk tokens replaced by [hidden]), `off`, or `full` "
            "(the paths as requested, codes included: for debugging; docs/data-protection.md)."
        ),
    )
    trusted_proxies: Annotated[tuple[str, ...], NoDecode] = Field(
        default=(),
        description=(
            "Addresses or networks (comma-separated, e.g. 127.0.0.1,10.0.0.0/24) of the reverse "
            "proxies in front of trustlab. Only requests from these may name the client's address "
            "and scheme in X-Forwarded-For / X-Forwarded-Proto; by default nobody may, so no "
            "local process can choose the address the sign-in throttle counts."
        ),
    )

    @field_validator("trusted_proxies", mode="before")
    @classmethod
    def _proxy_networks(cls, value: object) -> tuple[str, ...]:
        items = value.split(",") if isinstance(value, str) else value
        if not isinstance(items, list | tuple):
            raise ValueError("give addresses or networks separated by commas")
        networks = []
        for item in items:
            text = str(item).strip()
            if not text:
                continue
            try:
                networks.append(
                    str(ipaddress.ip_network(text, strict=False))
                    if "/" in text
                    else str(ipaddress.ip_address(text))
                )
            except ValueError:
                raise ValueError(f"{text!r} is not an IP address or network") from None
        return tuple(networks)

    @field_validator("sqlite_synchronous")
    @classmethod
    def _known_synchronous(cls, value: str) -> str:
        upper = value.upper()
        if upper not in {"OFF", "NORMAL", "FULL", "EXTRA"}:
            raise ValueError("must be one of OFF, NORMAL, FULL, EXTRA")
        return upper

    @property
    def is_sqlite(self) -> bool:
        """Whether the configured database is SQLite (one process, file-based)."""
        return self.database_url.startswith("sqlite")

    @cached_property
    def secret(self) -> bytes:
        """The signing key: the configured one, or one generated once and kept in var/."""
        if self.secret_key is not None:
            return self.secret_key.get_secret_value().encode()
        path = self.var_dir / "secret_key"
        if not path.exists():
            # Several workers may start at once: write aside, then link atomically; the loser
            # of the race simply reads the winner's key.
            self.var_dir.mkdir(parents=True, exist_ok=True)
            draft = path.with_name(f"secret_key.{os.getpid()}.tmp")
            draft.touch(mode=0o600)
            draft.write_text(secrets.token_urlsafe(48))
            try:
                os.link(draft, path)
            except FileExistsError:
                pass
            finally:
                draft.unlink()
        return path.read_text().strip().encode()
