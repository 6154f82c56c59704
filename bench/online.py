"""An online study at scale: hundreds of simulated participants at once through the public link.

Each participant is ``trustlab bots --online``'s (app/bots_online.py): a browser of its own that
joins from the platform's link, loads and submits every questionnaire page, starts each session in
the room and answers the robot over the room's socket, at a person's pace (exponential draws with
these means): ``--per-item`` seconds for each questionnaire item (3: above the 2 s per item under
which the study's data-quality rules flag speeding), ``--walk`` seconds to the next zone (5) and
``--think`` seconds before each submission, start and answer (2). A level's participants arrive
evenly over ``--arrivals`` seconds (60, as a platform's first wave does; 0: all in the same
moment), and each stays for the whole study, so the level is the number in the study at once
(reported as ``most_at_once``). ``--per-item 0 --walk 0 --arrivals 0`` is a stress load: every
participant at a machine's pace but for ``--think``, all arriving together.

Reported per level (participants at once): p50/p95/p99 of page loads (``all_pages``: the link's
page, ``/online`` and the questionnaire pages, also each apart), of submissions (``form``), of
session starts and of answers (``answer``), errors, participants completed,
answers lost or doubled (the answers the bots were told of against the answers stored, and
prompts without their answer), the servers' memory (RSS of every server process, sampled each
second: the peak above the idle server, per participant), and whether ``trustlab verify`` finds the
study clean. Levels run in order until one's p95 of page loads or answers exceeds 1 s: the load
at which it first does is reported.

    .venv/bin/python -m bench.online                                    # SQLite, 1 worker
    .venv/bin/python -m bench.online --postgres postgresql+psycopg://postgres@127.0.0.1:5432/test
    .venv/bin/python -m bench.online --postgres URL --workers 4
    .venv/bin/python -m bench.online --postgres URL --nginx             # two servers, one nginx
    .venv/bin/python -m bench.online --per-item 0 --walk 0 --arrivals 0 # the stress load
    .venv/bin/python -m bench.online --levels 20 --arrivals 5           # a quick look

``--nginx`` starts two ``trustlab serve``-like servers (``--workers`` each) sharing one
PostgreSQL behind Debian's nginx, which sends each request to the next server in turn: every
participant's requests alternate between the two, and their events travel through PostgreSQL's
LISTEN/NOTIFY. nginx must be installed (``apt-get install nginx-light``).

The study is the shipped protocol online, with a familiarisation run and ``--sessions`` sessions of
``--runs`` runs (default 2 and 1: about 20 requests per participant, a few minutes a level).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections import defaultdict
from contextlib import ExitStack
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sqlalchemy import func, select  # noqa: E402

from app import schema  # noqa: E402
from app.bots import BotConfig  # noqa: E402
from app.bots_online import HUMAN_PACE, Pace, run_online_bots  # noqa: E402
from app.db import Database  # noqa: E402
from app.protocol import default_protocol, parse_protocol  # noqa: E402
from app.services import studies  # noqa: E402
from app.services.audit import Actor  # noqa: E402
from app.services.sessions import verify  # noqa: E402
from app.services.staff import users  # noqa: E402
from app.tables import Answer, OnlineParticipation, OnlineStatus, Prompt, Role  # noqa: E402
from bench.api import PASSWORD, bench_database, percentile  # noqa: E402
from tests.servers import ServerProcess, free_port  # noqa: E402

SYSTEM = Actor.system("bench")
ONLINE = """
[online]
id_parameter = "PROLIFIC_PID"
parameters = ["STUDY_ID", "SESSION_ID"]
completion_url = "https://app.prolific.com/submissions/complete?cc={code}"
completion_code = "BENCH1"
time_limit_minutes = 240
"""
LIMIT_SECONDS = 1.0
"""A level whose p95 of page loads or answers exceeds this: the load the server no longer holds."""


def online_protocol(sessions: int, runs: int) -> str:
    """The shipped protocol (Exp3 in both conditions: the meta-policy's cost is bench/api.py's)
    run online with a shorter schedule."""
    text = default_protocol().source_text.replace('learner = "meta"', 'learner = "exp3"')
    for old, new in {
        "sessions = 4": f"sessions = {sessions}",
        "runs_per_session = 3": f"runs_per_session = {runs}",
    }.items():
        if old not in text:
            raise SystemExit(f"error: the shipped protocol no longer says {old!r}; update bench")
        text = text.replace(old, new)
    return text + ONLINE


def prepare(url: str, levels: list[int], sessions: int, runs: int) -> None:
    """Migrate; an admin for the bots; one online study per level (so each level starts empty)."""
    database = Database(url)
    schema.upgrade(database)
    with database.writing() as db:
        users.create_user(db, username="bench", role=Role.ADMIN, password=PASSWORD, actor=SYSTEM)
    for level in levels:
        with database.writing() as db:
            studies.create_study(
                db,
                name=f"online-{level}",
                loaded=parse_protocol(online_protocol(sessions, runs)),
                actor=SYSTEM,
            )
    database.dispose()


class MemorySampler:
    """The resident memory of every server process (the servers and their workers), sampled
    once a second on a thread of its own."""

    def __init__(self, roots: list[int]) -> None:
        self.roots = roots
        self.samples: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def resident(self) -> int:
        """Bytes resident in the roots and their descendants now."""
        children: dict[int, list[int]] = defaultdict(list)
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                children[parent].append(int(entry.name))
        total, pending = 0, list(self.roots)
        while pending:
            pid = pending.pop()
            pending.extend(children.get(pid, []))
            try:
                pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
            except (OSError, IndexError, ValueError):
                continue
            total += pages * os.sysconf("SC_PAGE_SIZE")
        return total

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            self.samples.append(self.resident())

    def __enter__(self) -> MemorySampler:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()


def nginx_in_front(
    servers: list[ServerProcess], directory: Path
) -> tuple[subprocess.Popen[bytes], str]:
    """Debian's nginx on a free port, sending requests to ``servers`` in turn (WebSockets too)."""
    binary = shutil.which("nginx") or "/usr/sbin/nginx"
    if not Path(binary).exists():
        raise SystemExit("error: --nginx needs Debian's nginx: apt-get install nginx-light")
    port = free_port()
    upstream = "\n".join(f"    server 127.0.0.1:{server.port};" for server in servers)
    (directory / "logs").mkdir(exist_ok=True)
    config = directory / "nginx.conf"
    config.write_text(
        f"""
worker_processes 1;
pid {directory}/nginx.pid;
error_log {directory}/logs/error.log warn;
events {{ worker_connections 4096; }}
http {{
  access_log off;
  client_body_temp_path {directory}/body;
  proxy_temp_path {directory}/proxy;
  fastcgi_temp_path {directory}/fastcgi;
  uwsgi_temp_path {directory}/uwsgi;
  scgi_temp_path {directory}/scgi;
  upstream trustlab {{
{upstream}
    keepalive 64;
  }}
  map $http_upgrade $connection_upgrade {{ default upgrade; '' ''; }}
  server {{
    listen 127.0.0.1:{port};
    location / {{
      proxy_pass http://trustlab;
      proxy_http_version 1.1;
      proxy_set_header Host $host;
      proxy_set_header Upgrade $http_upgrade;
      proxy_set_header Connection $connection_upgrade;
      proxy_buffering off;
      proxy_read_timeout 3600s;
    }}
  }}
}}
"""
    )
    process = subprocess.Popen(
        [binary, "-p", str(directory), "-c", str(config), "-g", "daemon off;"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=1) as reply:
                if reply.status == 200:
                    return process, f"http://127.0.0.1:{port}"
        except OSError:
            time.sleep(0.1)
    process.terminate()
    raise SystemExit(f"error: nginx did not answer on port {port} (see {directory}/logs)")


def stop_nginx(process: subprocess.Popen[bytes]) -> None:
    """Let nginx finish what it is doing, then go."""
    process.send_signal(signal.SIGQUIT)
    process.wait(10)


def stored(url: str, study: str) -> dict[str, Any]:
    """What the database holds of a level: completed participations, answers, unanswered prompts
    and whether ``trustlab verify`` finds the study clean."""
    database = Database(url)
    try:
        with database.read_session() as db:
            found = studies.get_study(db, study)
            completed = db.scalar(
                select(func.count())
                .select_from(OnlineParticipation)
                .where(
                    OnlineParticipation.study_id == found.id,
                    OnlineParticipation.status == OnlineStatus.COMPLETED,
                )
            )
            answers = db.scalar(select(func.count()).select_from(Answer))
            prompts = db.scalar(select(func.count()).select_from(Prompt))
            report = verify.verify_study(db, study_name=study)
        return {
            "completed": completed,
            "answers": answers,
            "prompts": prompts,
            "verify_ok": report.ok,
            "findings": [str(f) for f in report.findings][:3],
        }
    finally:
        database.dispose()


def level_figures(
    url: str,
    base: str,
    level: int,
    pace: Pace,
    arrivals: float,
    seed: int,
    memory: MemorySampler,
) -> dict[str, Any]:
    """Run one level (``level`` participants at once) and return its figures."""
    study = f"online-{level}"
    latencies: dict[str, list[float]] = defaultdict(list)
    answers_before = stored(url, study)["answers"]
    idle = memory.resident()
    first_sample = len(memory.samples)
    config = BotConfig(
        url=base,
        study=study,
        participants=level,
        username="bench",
        password=PASSWORD,
        concurrency=level,
        seed=seed,
        station_prefix=f"bench{level}",
    )
    began = time.perf_counter()
    summary = asyncio.run(
        run_online_bots(
            config,
            pace=pace,
            arrivals_seconds=arrivals,
            record=lambda kind, seconds: latencies[kind].append(seconds),
        )
    )
    seconds = time.perf_counter() - began
    peak = max(memory.samples[first_sample:], default=idle)
    after = stored(url, study)
    answers = after["answers"] - answers_before
    figures: dict[str, Any] = {
        "participants": level,
        "most_at_once": summary.most_at_once,
        "completed": summary.completed,
        "seconds": round(seconds, 1),
        "errors": len(summary.errors),
        "first_error": summary.errors[0] if summary.errors else None,
        "answers_told": summary.steps,
        "answers_stored": answers,
        "answers_lost": max(0, summary.steps - answers),
        "answers_doubled": max(0, answers - summary.steps),
        "verify_ok": after["verify_ok"],
        "memory_idle_mb": round(idle / 2**20, 1),
        "memory_peak_mb": round(peak / 2**20, 1),
        "memory_per_participant_kb": round((peak - idle) / 1024 / max(level, 1), 1),
    }
    loads = [*latencies.get("join", []), *latencies.get("online", []), *latencies.get("page", [])]
    latencies["all_pages"] = loads
    for kind in ("all_pages", "join", "online", "page", "form", "start", "prompt", "answer"):
        samples = latencies.get(kind, [])
        figures[kind] = {
            "count": len(samples),
            "p50_ms": round(percentile(samples, 0.50), 1) if samples else None,
            "p95_ms": round(percentile(samples, 0.95), 1) if samples else None,
            "p99_ms": round(percentile(samples, 0.99), 1) if samples else None,
        }
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--postgres", help="maintenance URL; runs against PostgreSQL instead")
    parser.add_argument(
        "--workers", type=int, help="uvicorn workers per server (default 1 SQLite, 2 PG)"
    )
    parser.add_argument(
        "--nginx", action="store_true", help="two servers behind nginx (PostgreSQL)"
    )
    parser.add_argument(
        "--levels",
        default="200,400",
        help="participants at once, one level after another (default 200,400)",
    )
    for option, field, what in (
        ("--think", "action", "mean pause before an action"),
        ("--per-item", "per_item", "mean pause per questionnaire item"),
        ("--walk", "walk", "mean walk to a zone"),
    ):
        default = getattr(HUMAN_PACE, field)
        parser.add_argument(
            option, type=float, default=default, help=f"{what}, seconds (default {default:g})"
        )
    parser.add_argument(
        "--arrivals",
        type=float,
        default=60.0,
        help="a level's participants arrive evenly over this many seconds (default 60)",
    )
    parser.add_argument("--sessions", type=int, default=2)
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    levels = [int(level) for level in args.levels.split(",") if level.strip()]
    if not levels or min(levels) < 1:
        raise SystemExit("error: --levels are participant counts, e.g. 200,400")
    if args.nginx and not args.postgres:
        raise SystemExit(
            "error: --nginx shares one PostgreSQL between two servers: give --postgres"
        )
    workers = args.workers or (2 if args.postgres else 1)
    try:
        pace = Pace(action=args.think, per_item=args.per_item, walk=args.walk)
    except ValueError as error:
        raise SystemExit(f"error: {error}") from None
    if args.arrivals < 0:
        raise SystemExit("error: --arrivals is seconds ≥ 0")
    engine = "postgresql" if args.postgres else "sqlite"
    results: list[dict[str, Any]] = []
    first_over: int | None = None
    with (
        tempfile.TemporaryDirectory() as tmp,
        bench_database(args.postgres, tmp, "online") as url,
        ExitStack() as running,
    ):
        print(f"preparing {len(levels)} studies on {engine}…", file=sys.stderr)
        prepare(url, levels, args.sessions, args.runs)
        servers = [
            # started afresh, as `trustlab serve` is (not forked from the tests' preloader)
            ServerProcess(url, Path(tmp) / f"var-{n}", workers=workers, preload=False)
            for n in range(2 if args.nginx else 1)
        ]
        for server in servers:
            server.start()
            running.callback(server.stop)
        base = servers[0].url
        if args.nginx:
            proxy, base = nginx_in_front(servers, Path(tmp))
            running.callback(stop_nginx, proxy)
        roots = [server.process.pid for server in servers if server.process is not None]
        with MemorySampler(roots) as memory:
            for level in levels:
                print(f"{level} participants at once…", file=sys.stderr)
                figures = level_figures(url, base, level, pace, args.arrivals, args.seed, memory)
                results.append(figures)
                print(json.dumps(figures), file=sys.stderr)
                pages, answers = figures["all_pages"]["p95_ms"], figures["answer"]["p95_ms"]
                worst = max(pages or 0.0, answers or 0.0)
                if worst > LIMIT_SECONDS * 1000:
                    first_over = level
                    break
    result = {
        "engine": engine,
        "workers_per_server": workers,
        "servers": 2 if args.nginx else 1,
        "behind_nginx": args.nginx,
        "pace_s": {"action": pace.action, "per_item": pace.per_item, "walk": pace.walk},
        "arrivals_s": args.arrivals,
        "schedule": {"sessions": args.sessions, "runs_per_session": args.runs},
        "levels": results,
        "first_level_over_1s_p95": first_over,
    }
    if args.json:
        print(json.dumps(result))
        return
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
