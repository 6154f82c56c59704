"""The demo study that ``make run`` fills with simulated participants on first start.

A lab trying trustlab should see a dashboard with data before running a single session. On an
empty database, ``trustlab init`` creates a second study, ``demo``, from the shipped protocol and
an internal admin account for the bots, and leaves a plan in ``var/demo-pending.json`` (readable
by the owner only). The next ``trustlab serve`` sees the plan, waits until the server answers, runs
:func:`app.bots.run_bots` against itself over real HTTP and WebSockets, then deactivates the bots'
account and deletes the plan, so the demo happens once. ``trustlab init --no-demo`` skips it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import httpx
from sqlalchemy.orm import Session

from app.bots import BotConfig, BotSummary, run_bots
from app.db import Database
from app.errors import Conflict
from app.protocol import default_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.sessions import stations
from app.services.staff import accounts, users
from app.settings import Settings
from app.tables import Role

DEMO_STUDY = "demo"
DEMO_ACCOUNT = "demo-bots"
DEMO_PARTICIPANTS = 8
DEMO_STATIONS = 4
DEMO_STATION_PREFIX = "demo"
PLAN_FILE = "demo-pending.json"


@dataclass(frozen=True)
class DemoPlan:
    """What the first ``trustlab serve`` has to do."""

    study: str
    username: str
    password: str
    participants: int


def plan_path(settings: Settings) -> Path:
    return settings.var_dir / PLAN_FILE


def plan_demo(db: Session, settings: Settings, actor: Actor) -> DemoPlan:
    """Create the demo study and the bots' account; write the plan for ``trustlab serve``."""
    loaded = default_protocol()
    title = f"Demo with simulated participants: {loaded.protocol.study.title}"
    studies.create_study(db, name=DEMO_STUDY, loaded=loaded, actor=actor, title=title[:200])
    password = secrets.token_urlsafe(18)
    users.create_user(db, username=DEMO_ACCOUNT, role=Role.ADMIN, password=password, actor=actor)
    plan = DemoPlan(DEMO_STUDY, DEMO_ACCOUNT, password, DEMO_PARTICIPANTS)
    path = plan_path(settings)
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w", encoding="utf-8") as out:
        json.dump(plan.__dict__, out)
    return plan


def retire(plan: DemoPlan, settings: Settings, echo: Callable[[str], None]) -> None:
    """After the demo: disable the bots' account, archive the bots' stations (a lab's station
    list shows its own) and remove the plan (it holds the password). Should the bots' account
    have become the only active admin meanwhile, it stays enabled: there is always an active
    admin (app.services.staff.accounts)."""
    database = Database(settings.database_url)
    actor = Actor.system("demo")
    try:
        with database.writing() as db:
            for station in stations.list_stations(db, archived=False):
                if _is_demo_station(station.name) and station.participant_id is None:
                    stations.set_archived(db, station_name=station.name, archived=True, actor=actor)
        with database.writing() as db:
            accounts.disable_user(db, username=plan.username, actor=actor)
    except Conflict as exc:
        echo(f"demo: the bots' account stays enabled: {exc.message}")
    finally:
        database.dispose()
    plan_path(settings).unlink(missing_ok=True)


def _is_demo_station(name: str) -> bool:
    prefix, _, number = name.rpartition("-")
    return prefix == DEMO_STATION_PREFIX and number.isdigit() and int(number) <= DEMO_STATIONS


def pending_demo(settings: Settings) -> DemoPlan | None:
    """The plan left by ``trustlab init``, if the demo has not run yet."""
    try:
        return DemoPlan(**json.loads(plan_path(settings).read_text(encoding="utf-8")))
    except (FileNotFoundError, json.JSONDecodeError, TypeError):
        return None


def wait_until_up(url: str, timeout: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/healthz", timeout=2.0).status_code == 200:
                return True
        except httpx.TransportError:
            pass
        time.sleep(0.25)
    return False


class QuietWhileFilling(logging.Filter):
    """Keeps the server's request log quiet while the demo fills its study: its bots make
    hundreds of requests, and their lines would scroll away the admin's once-only password that
    ``trustlab init`` printed just above. Attached to ``uvicorn.access`` by ``trustlab serve``."""

    def __init__(self) -> None:
        super().__init__()
        self.filling = threading.Event()

    def filter(self, record: logging.LogRecord) -> bool:
        return not self.filling.is_set()


def run_demo(
    plan: DemoPlan,
    url: str,
    settings: Settings,
    echo: Callable[[str], None],
    quiet: QuietWhileFilling | None = None,
) -> BotSummary | None:
    """Fill the demo study through the running server at ``url``; then retire the plan.
    ``quiet``: the request log's filter, set while the bots run."""
    if not wait_until_up(url):
        echo("demo: the server did not come up; the demo study stays empty (restart to retry)")
        return None
    echo(
        f"demo: {plan.participants} simulated participants are filling the '{plan.study}' study…"
        + (" (the request log resumes when it is done)" if quiet is not None else "")
    )
    if quiet is not None:
        quiet.filling.set()
    try:
        summary = asyncio.run(
            run_bots(
                BotConfig(
                    url=url,
                    study=plan.study,
                    participants=plan.participants,
                    username=plan.username,
                    password=plan.password,
                    concurrency=DEMO_STATIONS,
                    noise=0.1,
                    seed=1,
                    station_prefix=DEMO_STATION_PREFIX,
                )
            )
        )
    finally:
        if quiet is not None:
            quiet.filling.clear()
    retire(plan, settings, echo)
    problems = ""
    if summary.errors:
        problems = f", {len(summary.errors)} errors (first: {summary.errors[0]})"
    echo(
        f"demo: done in {summary.seconds:.0f} s: {summary.completed} participants, "
        f"{summary.steps} answers, {summary.questionnaires} questionnaires{problems}"
    )
    return summary
