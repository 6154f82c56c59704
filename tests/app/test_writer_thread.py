"""On SQLite a robot's writes take turns on one writer thread (app.db.WriterThread); reads, and
everything on PostgreSQL, use the shared thread pool."""

from __future__ import annotations

import asyncio
import contextvars
import threading
import time
from pathlib import Path
from typing import Any

import anyio
import pytest
from sqlalchemy import event, text
from sqlalchemy.exc import OperationalError

from app import db as db_module
from app.db import WRITE_OPTION, WRITER_WAIT_SECONDS, Database, WriterThread, _writer_wait_left
from tests.conftest import Lab

BACKGROUND = ("trustlab-activity", "trustlab-checkpoint")
REQUEST_ID: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="none")


def test_a_robots_writes_take_turns_on_one_thread_on_sqlite_only(lab: Lab) -> None:
    """Prompts and answers write on SQLite's writer thread; the station state is a read and goes
    to the thread pool, as everything does on PostgreSQL."""
    begun: list[tuple[str, bool]] = []

    def note(conn: Any) -> None:
        name = threading.current_thread().name
        if name in BACKGROUND:  # the activity recorder flushes device notes every few seconds
            return
        begun.append((name, bool(conn.get_execution_options().get(WRITE_OPTION, False))))

    database = lab.app.state.database
    engine = database.engine
    event.listen(engine, "begin", note)
    try:
        lab.enrol_and_assign()
        lab.start_session()
        begun.clear()
        state = lab.robot.get("/api/v1/station").json()
        for category in state["expected"]["categories"]:
            step = lab.prompt(category)
            lab.answer(step["step_id"], "yes")
    finally:
        event.remove(engine, "begin", note)

    writes = {name for name, write in begun if write}
    reads = {name for name, write in begun if not write}
    assert len([1 for _, write in begun if write]) == 2 * len(state["expected"]["categories"])
    assert reads and not any(name.startswith("trustlab-writer") for name in reads)
    if database.is_sqlite:
        assert len(writes) == 1 and next(iter(writes)).startswith("trustlab-writer")
    else:
        assert not any(name.startswith("trustlab-writer") for name in writes)


def test_units_of_work_run_one_at_a_time_in_the_order_they_came() -> None:
    writer = WriterThread()
    running = 0
    overlaps = 0
    order: list[int] = []

    def unit(number: int) -> int:
        nonlocal running, overlaps
        running += 1
        overlaps += running > 1
        time.sleep(0.002)
        order.append(number)
        running -= 1
        return number * 10

    async def main() -> list[int]:
        return await asyncio.gather(*(writer.run(unit, n) for n in range(20)))

    try:
        assert asyncio.run(main()) == [n * 10 for n in range(20)]
    finally:
        writer.stop()
    assert overlaps == 0 and order == list(range(20))


def test_the_callers_context_variables_and_exceptions_cross_over() -> None:
    writer = WriterThread()

    def read_request_id() -> str:
        return REQUEST_ID.get()

    def fail() -> None:
        raise LookupError("from the writer thread")

    async def main() -> tuple[str, str]:
        REQUEST_ID.set("req-7")
        seen = await writer.run(read_request_id)
        try:
            await writer.run(fail)
        except LookupError as error:
            return seen, str(error)
        raise AssertionError("the writer thread's exception was lost")

    try:
        assert asyncio.run(main()) == ("req-7", "from the writer thread")
    finally:
        writer.stop()


def test_a_cancelled_caller_waits_until_its_unit_of_work_has_ended() -> None:
    """As with run_in_threadpool: a caller cancelled through anyio's cancel scopes (a request's
    task group) is let go only once its work has ended, so the admission slot it holds is held
    exactly as long as the work runs."""
    writer = WriterThread()
    started, release = threading.Event(), threading.Event()
    events: list[str] = []

    def unit() -> None:
        started.set()
        release.wait(10)
        events.append("work ended")

    async def caller(scope: anyio.CancelScope) -> None:
        try:
            with scope:
                await writer.run(unit)
        finally:
            events.append("caller let go")

    async def main() -> None:
        scope = anyio.CancelScope()
        async with anyio.create_task_group() as group:
            group.start_soon(caller, scope)
            while not started.is_set():
                await anyio.sleep(0.001)
            scope.cancel()
            await anyio.sleep(0.05)
            events.append("cancelled 50 ms ago")
            release.set()

    try:
        anyio.run(main)
    finally:
        writer.stop()
    assert events == ["cancelled 50 ms ago", "work ended", "caller let go"]


def test_a_natively_cancelled_caller_does_not_drop_its_queued_work() -> None:
    """A WebSocket's tasks are cancelled with task.cancel(): the caller goes at once, but its
    unit of work, still waiting for its turn, runs all the same (as a thread-pool hop's did)."""
    writer = WriterThread()
    started, release = threading.Event(), threading.Event()
    ran: list[str] = []

    def first() -> None:
        started.set()
        release.wait(10)
        ran.append("first")

    def queued() -> None:
        ran.append("queued")

    async def main() -> bool:
        running = asyncio.create_task(writer.run(first))
        while not started.is_set():
            await asyncio.sleep(0.001)
        waiting = asyncio.create_task(writer.run(queued))
        await asyncio.sleep(0.01)
        waiting.cancel()
        try:
            await waiting
        except asyncio.CancelledError:
            cancelled = True
        release.set()
        await running
        return cancelled

    try:
        assert asyncio.run(main()) is True
    finally:
        writer.stop()
    assert ran == ["first", "queued"]


def test_waiting_for_the_writer_threads_turn_counts_towards_the_write_lock_wait() -> None:
    """Writes queued behind a stuck write lock fail together after the wait, not one wait
    after another. The clock is the test's: the unit ahead "takes" 5 s by advancing it."""
    now = [1000.0]
    writer = WriterThread(clock=lambda: now[0])
    ahead_started, queued = threading.Event(), threading.Event()

    def slow() -> None:
        ahead_started.set()
        queued.wait(10)  # the second unit is queued (at t = 1000) before this one ends
        now[0] += 5.0

    async def main() -> float:
        first = asyncio.ensure_future(writer.run(slow))
        await asyncio.to_thread(ahead_started.wait, 10)
        second = asyncio.ensure_future(writer.run(_writer_wait_left))
        await asyncio.sleep(0)  # let the second unit be submitted (it reads the clock first)
        queued.set()
        await first
        return await second

    try:
        left_after_queueing = asyncio.run(main())
    finally:
        writer.stop()
    assert _writer_wait_left() == WRITER_WAIT_SECONDS  # off the writer thread: the whole wait
    assert left_after_queueing == WRITER_WAIT_SECONDS - 5.0


def test_a_queued_write_behind_a_held_lock_is_refused_once_the_wait_is_over(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(db_module, "WRITER_WAIT_SECONDS", 0.3)
    database = Database(f"sqlite:///{tmp_path}/held.sqlite3")
    holding, release = threading.Event(), threading.Event()

    def hold_the_write_lock() -> None:
        with database.write_session() as session:
            session.execute(text("SELECT 1"))  # BEGIN IMMEDIATE: the writer queue is ours
            holding.set()
            release.wait(10)

    def write() -> str:
        with database.write_session() as session:
            session.execute(text("SELECT 1"))
        return "wrote"

    holder = threading.Thread(target=hold_the_write_lock)
    holder.start()
    holding.wait(10)

    async def main() -> list[object]:
        runs = (database.run_unit_of_work(write, write=True) for _ in range(3))
        return await asyncio.gather(*runs, return_exceptions=True)

    try:
        outcomes = asyncio.run(main())
    finally:
        release.set()
        holder.join(10)
        database.finish_requests()
        database.dispose()
    assert all(isinstance(o, OperationalError) and "writer queue" in str(o) for o in outcomes)


def test_finishing_requests_ends_the_writer_thread_after_its_queued_work(tmp_path: Path) -> None:
    """And a later write starts a new writer thread."""
    database = Database(f"sqlite:///{tmp_path}/finish.sqlite3")
    names: list[str] = []

    def unit() -> None:
        time.sleep(0.01)
        names.append(threading.current_thread().name)

    async def queue(count: int) -> None:
        await asyncio.gather(*(database.run_unit_of_work(unit, write=True) for _ in range(count)))

    try:
        asyncio.run(queue(3))
        database.finish_requests()
        assert len(names) == 3 and len(set(names)) == 1 and names[0].startswith("trustlab-writer")
        assert not any(t.name == names[0] for t in threading.enumerate())
        asyncio.run(queue(1))
        database.finish_requests()
        assert len(names) == 4
    finally:
        database.dispose()


def test_sqlite_hands_out_the_connection_returned_last(tmp_path: Path) -> None:
    """The writer thread keeps the connection whose page cache its last write left valid."""
    database = Database(f"sqlite:///{tmp_path}/lifo.sqlite3")
    try:
        first = database.engine.raw_connection()
        second = database.engine.raw_connection()
        first_driver, second_driver = first.driver_connection, second.driver_connection
        first.close()
        second.close()
        again = database.engine.raw_connection()
        assert again.driver_connection is second_driver is not first_driver
        again.close()
    finally:
        database.dispose()
