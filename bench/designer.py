"""The designer where people wait (issue 50): each section's page, the live check that runs as
one types (htmx posts the whole form after a pause), and a save, p50/p95 in milliseconds.

In process (the app over Starlette's test client, SQLite in a temporary folder) on a draft of
the English-and-Swedish shipped protocol, whose questionnaires section is the largest form (an
input per item setting). The check is what a person waits on after each pause in typing.

    .venv/bin/python bench/designer.py
    .venv/bin/python bench/designer.py --repeat 40
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastapi.testclient import TestClient

from app import schema
from app.db import Database
from app.main import create_app
from app.protocol import shipped_protocol
from app.protocol_forms import ENTRIES, SECTIONS, section_fields
from app.services import studies
from app.services.audit import Actor
from app.services.staff import users
from app.settings import Settings
from app.tables import Role, StudyPhase

PASSWORD = "designer bench password"


def _form(text: str, slug: str) -> dict[str, Any]:
    section = next(s for s in SECTIONS if s.slug == slug)
    form: dict[str, Any] = {}
    for top in section_fields(section, text):
        for made in top.walk():
            if made.kind == "list":
                form[made.name + ENTRIES] = str(len(made.children))
            elif made.kind == "checkbox":
                if made.value:
                    form[made.name] = "on"
            elif made.kind != "group":
                form[made.name] = made.value
    return form


def _ms(samples: list[float]) -> str:
    ordered = sorted(samples)
    p95 = ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))]
    return f"p50 {statistics.median(ordered) * 1000:7.1f}  p95 {p95 * 1000:7.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=20, help="requests per measure")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="trustlab-designer-bench-"))
    url = f"sqlite:///{folder / 'bench.sqlite3'}"
    database = Database(url)
    schema.upgrade(database)
    loaded = shipped_protocol("fast_adaptation_trust_sv.toml")
    with database.writing() as db:
        studies.create_study(
            db, name="bench", loaded=loaded, actor=Actor.system(), phase=StudyPhase.DRAFT
        )
        users.create_user(
            db, username="designer", role=Role.ADMIN, password=PASSWORD, actor=Actor.system()
        )
    app = create_app(Settings(_env_file=None, database_url=url, secret_key="d" * 40))
    with TestClient(app) as client:
        signed = client.post("/api/v1/session", json={"username": "designer", "password": PASSWORD})
        client.headers["X-CSRF-Token"] = signed.json()["csrf_token"]
        text = loaded.source_text
        print(f"designer, {args.repeat} requests each, milliseconds (in process, SQLite)")
        for section in SECTIONS:
            page_times, check_times = [], []
            form = _form(text, section.slug)
            base = re.search(
                r'name="base" value="([0-9a-f]{64})"',
                client.get(f"/admin/studies/bench/design/{section.slug}").text,
            )
            assert base is not None
            form["base"] = base.group(1)
            for _ in range(args.repeat):
                started = time.perf_counter()
                client.get(f"/admin/studies/bench/design/{section.slug}")
                page_times.append(time.perf_counter() - started)
                started = time.perf_counter()
                client.post(f"/admin/studies/bench/design/{section.slug}/check", data=form)
                check_times.append(time.perf_counter() - started)
            fields = sum(1 for top in section_fields(section, text) for _ in top.leaves())
            print(
                f"{section.slug:<15} {fields:4d} fields  page {_ms(page_times)}"
                f"  check {_ms(check_times)}"
            )
        saves = []
        for number in range(args.repeat):
            page = client.get("/admin/studies/bench/design/speech").text
            base = re.search(r'name="base" value="([0-9a-f]{64})"', page)
            assert base is not None
            form = _form(client.get("/studies/bench/protocol.toml").text, "speech")
            form |= {"base": base.group(1), "speech.attempts": str(2 + number % 2)}
            started = time.perf_counter()
            saved = client.post("/admin/studies/bench/design/speech", data=form)
            saves.append(time.perf_counter() - started)
            assert "Saved as version" in saved.text, saved.text[-500:]
        print(f"save (speech, redirect followed)     {_ms(saves)}")


if __name__ == "__main__":
    main()
