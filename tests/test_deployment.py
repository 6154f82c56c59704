"""docker-compose.yml and the Dockerfile: validated here, since no Docker engine runs in CI."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from app.settings import REPO_ROOT, Settings

COMPOSE = yaml.safe_load((REPO_ROOT / "docker-compose.yml").read_text())
DOCKERFILE = (REPO_ROOT / "Dockerfile").read_text()


def test_compose_runs_postgres_16_and_the_app() -> None:
    services = COMPOSE["services"]
    assert set(services) == {"postgres", "app"}
    assert services["postgres"]["image"] == "postgres:16"
    assert services["app"]["build"] == "."
    assert services["app"]["depends_on"]["postgres"]["condition"] == "service_healthy"


def test_compose_environment_points_the_app_at_postgres() -> None:
    env = COMPOSE["services"]["app"]["environment"]
    assert env["TRUSTLAB_DATABASE_URL"].startswith("postgresql+psycopg://trustlab:")
    assert env["TRUSTLAB_DATABASE_URL"].endswith("@postgres:5432/trustlab")
    assert "TRUSTLAB_ADMIN_PASSWORD" in env and ":?" in env["TRUSTLAB_ADMIN_PASSWORD"]
    assert "TRUSTLAB_SECRET_KEY" in env
    known = {f"TRUSTLAB_{name.upper()}" for name in Settings.model_fields} | {"TRUSTLAB_WORKERS"}
    assert set(env) <= known, "every TRUSTLAB_* variable must be a setting"


def test_compose_ports_volumes_and_healthchecks() -> None:
    services = COMPOSE["services"]
    assert services["app"]["ports"] == ["127.0.0.1:8000:8000"]
    assert "pgdata:/var/lib/postgresql/data" in services["postgres"]["volumes"]
    assert set(COMPOSE["volumes"]) == {"pgdata", "appdata"}
    assert "pg_isready" in " ".join(services["postgres"]["healthcheck"]["test"])
    assert "/healthz" in " ".join(services["app"]["healthcheck"]["test"])


def test_dockerfile_migrates_at_start_and_pins_everything() -> None:
    cmd = re.search(r"^CMD (.+)$", DOCKERFILE, re.MULTILINE)
    assert cmd and "trustlab init && exec trustlab serve --host 0.0.0.0" in cmd.group(1)
    assert "-r requirements.lock" in DOCKERFILE
    assert "npm ci" in DOCKERFILE
    assert "HEALTHCHECK" in DOCKERFILE and "/healthz" in DOCKERFILE
    assert re.search(r"^USER trustlab$", DOCKERFILE, re.MULTILINE)
    for asset in ("htmx.min.js", "plotly-cartesian.min.js", "swagger-ui-bundle.js"):
        assert asset in DOCKERFILE and asset in (REPO_ROOT / "Makefile").read_text()


def test_dockerignore_keeps_local_state_out() -> None:
    ignored = set((REPO_ROOT / ".dockerignore").read_text().split())
    assert {".venv", "node_modules", "var", ".env", ".git"} <= ignored
    assert Path(REPO_ROOT / "package-lock.json").exists()
