"""Test servers forked from one process that has already imported the app.

Each ``uvicorn`` started afresh spends about 2.5 s of CPU importing trustlab (scipy, pandas,
plotly...) before it can answer; a crash test restarts its server six times, and every browser
test starts one. A *preloader* does those imports once per test process and then forks a child
per server. Each child is still a process of its own, in a session of its own, with its own
environment (database URL, var dir, secret), working directory and log, running uvicorn's own
command line; SIGKILL kills it as it kills a server started with ``subprocess``. Only the
imports are shared, and they are read-only until the child changes them.

The preloader is a child of the test process (``python -m tests.preloaded``) and is told what to
do over its stdin, one JSON line a request, answering one JSON line each on its stdout:

- ``{"op": "fork", "program": "uvicorn", "argv": [...], "env": {...}, "cwd": ..., "log": ...}``:
  fork a server running that command line (``uvicorn`` or ``trustlab``), answer its ``pid``.
  The server is the preloader's child, so the test process watches it through a pidfd and asks
  the preloader to reap it:
- ``{"op": "reap", "pid": N}``: wait for that (exited) server, answer its wait ``status``.

When its stdin closes (the test process is gone) the preloader SIGKILLs the servers it still
has and exits, so no test server outlives its test run.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import importlib
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import traceback
from pathlib import Path
from typing import IO, Any

REPO_ROOT = Path(__file__).resolve().parents[1]
PRELOADED_MODULES = (
    "app.main",
    "uvicorn.main",
    "uvicorn.loops.auto",
    "uvicorn.protocols.http.auto",
    "uvicorn.protocols.websockets.auto",
    "uvicorn.lifespan.on",
)
"""What every server imports before it answers; imported once, in the preloader."""
PROGRAMS = {"uvicorn": "uvicorn.main", "trustlab": "app.cli"}
"""The command lines a preloaded process can run: each module's ``main()``, reading sys.argv as
the installed console script does."""
BASE_ENV_NAMES = ("PATH", "HOME")
"""The preloader's environment: only what a server's own is built on (tests.servers), so that
nothing it reads while importing differs from what a freshly started server would read."""


class ForkedServer:
    """A server forked by the preloader, watched like a ``subprocess.Popen``: ``pid``,
    ``poll()``, ``wait(timeout)`` (the process exits as any other; only reaping goes through
    the preloader, whose child it is)."""

    def __init__(self, preloader: Preloaded, pid: int) -> None:
        self.preloader = preloader
        self.pid = pid
        self.returncode: int | None = None
        self._pidfd: int | None = os.pidfd_open(pid)
        """Readable once the server has exited. Opened before the server can be reaped (the
        preloader reaps only when asked), so the pid cannot have been reused."""

    def poll(self) -> int | None:
        """The exit code if the server has exited, else None."""
        return self._reap_if_exited(timeout=0.0)

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the server to exit; ``subprocess.TimeoutExpired`` after ``timeout`` s."""
        code = self._reap_if_exited(timeout=timeout)
        if code is None:
            raise subprocess.TimeoutExpired(f"server {self.pid}", timeout or 0.0)
        return code

    def _reap_if_exited(self, timeout: float | None) -> int | None:
        if self._pidfd is None:
            return self.returncode
        readable, _, _ = select.select([self._pidfd], [], [], timeout)
        if not readable:
            return None
        status = self.preloader.request({"op": "reap", "pid": self.pid})["status"]
        os.close(self._pidfd)
        self._pidfd = None
        self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode


class Preloaded:
    """The test process's end of one preloader: ``fork(program, argv, env, cwd, log)`` starts
    ``program argv`` (``uvicorn`` or ``trustlab``) as a new process with that environment.
    Thread-safe (a crash test restarts its server from another thread)."""

    _shared: Preloaded | None = None
    _shared_lock = threading.Lock()

    @classmethod
    def shared(cls) -> Preloaded:
        """This test process's preloader, started on first use (again if it died)."""
        with cls._shared_lock:
            if cls._shared is None or cls._shared.process.poll() is not None:
                cls._shared = cls()
            return cls._shared

    def __init__(self) -> None:
        self.log_path = Path(tempfile.mkstemp(prefix="trustlab-preloader-", suffix=".log")[1])
        env = {name: os.environ[name] for name in BASE_ENV_NAMES if name in os.environ}
        with self.log_path.open("ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "tests.preloaded"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                env=env,
                cwd=REPO_ROOT,
            )
        self._lock = threading.Lock()
        atexit.register(self.close)

    def close(self) -> None:
        """Let the preloader go (it kills the servers it still has); its log goes with it
        unless it failed."""
        if self.process.stdin is not None and not self.process.stdin.closed:
            self.process.stdin.close()
        try:
            failed = self.process.wait(timeout=30) != 0
        except subprocess.TimeoutExpired:
            self.process.kill()
            failed = True
        if not failed:
            self.log_path.unlink(missing_ok=True)

    def fork(
        self, program: str, argv: list[str], *, env: dict[str, str], cwd: str, log: Path
    ) -> ForkedServer:
        """``program argv`` in a new process (a session of its own) with exactly ``env``."""
        assert program in PROGRAMS, program
        answer = self.request(
            {
                "op": "fork",
                "program": program,
                "argv": argv,
                "env": env,
                "cwd": cwd,
                "log": str(log),
            }
        )
        return ForkedServer(self, int(answer["pid"]))

    def request(self, message: dict[str, Any]) -> dict[str, Any]:
        """Send one request and read its answer (the preloader answers every request)."""
        assert self.process.stdin is not None and self.process.stdout is not None
        with self._lock:
            try:
                self.process.stdin.write(json.dumps(message).encode() + b"\n")
                self.process.stdin.flush()
                line = self.process.stdout.readline()
            except BrokenPipeError:
                line = b""
        if not line:
            raise RuntimeError(f"the preloader died: {self.log_path.read_text()[-2000:]}")
        answer: dict[str, Any] = json.loads(line)
        if "error" in answer:
            raise RuntimeError(f"the preloader refused {message['op']}: {answer['error']}")
        return answer


# The preloader itself: runs in its own process (``python -m tests.preloaded``).


def _serve_requests(requests: IO[bytes], answers: IO[bytes]) -> None:
    """Answer requests until stdin closes, then kill whatever servers are left."""
    children: set[int] = set()
    for line in requests:
        message = json.loads(line)
        try:
            if message["op"] == "fork":
                pid = os.fork()
                if pid == 0:
                    _become_server(message, requests, answers)
                children.add(pid)
                answer: dict[str, Any] = {"pid": pid}
            elif message["op"] == "reap":
                _, status = os.waitpid(message["pid"], 0)
                children.discard(message["pid"])
                answer = {"status": status}
            else:
                answer = {"error": f"unknown op {message['op']!r}"}
        except OSError as error:
            answer = {"error": repr(error)}
        answers.write(json.dumps(answer).encode() + b"\n")
        answers.flush()
    for pid in children:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pid, signal.SIGKILL)


def _become_server(message: dict[str, Any], requests: IO[bytes], answers: IO[bytes]) -> None:
    """In the forked child: become ``program argv`` as a fresh process would, never return."""
    code = 1
    try:
        os.setsid()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        requests.close()
        answers.close()
        log = os.open(message["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        nothing = os.open(os.devnull, os.O_RDONLY)
        os.dup2(nothing, 0)
        os.dup2(log, 1)
        os.dup2(log, 2)
        os.close(log)
        os.close(nothing)
        os.chdir(message["cwd"])
        os.environ.clear()
        os.environ.update(message["env"])
        sys.argv = [message["program"], *message["argv"]]
        importlib.import_module(PROGRAMS[message["program"]]).main()
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
    except BaseException:
        traceback.print_exc()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def main() -> None:
    """Import once, then fork servers on request."""
    # The protocol gets stdout's pipe to itself; anything printed goes to the log instead.
    answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    requests = sys.stdin.buffer
    for module in (*PRELOADED_MODULES, *PROGRAMS.values()):
        importlib.import_module(module)
    gc.freeze()  # the imports stay shared pages in every child instead of being copied by GC
    _serve_requests(requests, answers)


if __name__ == "__main__":
    main()
