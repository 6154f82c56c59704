"""Real trustlab servers in subprocesses, for crash, multi-worker, browser and load tests."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from app.settings import KEEP_ALIVE_SECONDS
from tests.preloaded import ForkedServer, Preloaded

FRESH_PROGRAMS = {
    "uvicorn": [sys.executable, "-m", "uvicorn"],
    "trustlab": [sys.executable, "-c", "from app.cli import main; main()"],
}
"""How each program starts from nothing, when not forked from the preloader."""


def free_port() -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class ServerProcess:
    """``uvicorn app.main:create_app`` (or another ``factory``) on a free port, startable, killable
    and restartable.

    Forked from this test process's preloader (tests.preloaded), which has imported the app
    already, unless ``source`` names another tree to serve (its modules are not the preloaded
    ones) or ``preload=False``: then ``python -m uvicorn`` starts from nothing."""

    def __init__(
        self,
        database_url: str,
        var_dir: Path,
        *,
        workers: int = 1,
        extra_env: dict[str, str] | None = None,
        factory: str = "app.main:create_app",
        source: Path | None = None,
        preload: bool = True,
    ) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.workers = workers
        self.factory = factory
        self.log_path = var_dir / f"server-{self.port}.log"
        var_dir.mkdir(parents=True, exist_ok=True)
        self.env = {
            "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
            "HOME": os.environ.get("HOME", "/tmp"),
            "TRUSTLAB_DATABASE_URL": database_url,
            "TRUSTLAB_VAR_DIR": str(var_dir),
            "TRUSTLAB_SECRET_KEY": "subprocess-test-secret-0123456789abcdef",
            **(extra_env or {}),
        }
        self.source = source
        """Serve the trustlab in this directory (a git worktree, say) instead of the one
        imported here: it comes first on the server's module path."""
        if source is not None:
            given = self.env.get("PYTHONPATH")
            self.env["PYTHONPATH"] = str(source) + (os.pathsep + given if given else "")
        self.preload = preload and source is None
        self.process: subprocess.Popen[bytes] | ForkedServer | None = None

    def command_line(self) -> tuple[str, list[str]]:
        """The program (``uvicorn`` or ``trustlab``) and its arguments."""
        arguments = [
            self.factory,
            "--factory",
            "--host",
            "127.0.0.1",
            "--port",
            str(self.port),
            "--log-level",
            "warning",
            "--timeout-graceful-shutdown",  # as `trustlab serve` does: live streams never end
            "1",
            "--timeout-keep-alive",  # as `trustlab serve` does
            str(KEEP_ALIVE_SECONDS),
        ]
        if self.workers > 1:
            arguments += ["--workers", str(self.workers)]
        return "uvicorn", arguments

    def start(self, timeout: float = 60.0) -> None:
        """Start and wait until /healthz answers 200."""
        program, arguments = self.command_line()
        if self.preload:
            self.process = Preloaded.shared().fork(
                program, arguments, env=self.env, cwd=os.getcwd(), log=self.log_path
            )
        else:
            with self.log_path.open("ab") as log:
                self.process = subprocess.Popen(
                    [*FRESH_PROGRAMS[program], *arguments],
                    env=self.env,
                    stdout=log,
                    stderr=log,
                    start_new_session=True,
                    cwd=self.source,
                )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited early: {self.log_path.read_text()[-2000:]}")
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"server did not start: {self.log_path.read_text()[-2000:]}")

    def kill(self) -> None:
        """SIGKILL the whole process group (workers included): no chance to clean up."""
        if self.process is not None and self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout=10)
        self.process = None

    def stop(self) -> None:
        """Stop gracefully (SIGTERM), or kill after a grace period."""
        if self.process is not None and self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.kill()
        self.process = None


class TrustlabServe(ServerProcess):
    """``trustlab serve`` itself (ServerProcess runs uvicorn's own command line, whose defaults
    trust X-Forwarded-For from loopback)."""

    def command_line(self) -> tuple[str, list[str]]:
        return "trustlab", ["serve", "--host", "127.0.0.1", "--port", str(self.port)]
