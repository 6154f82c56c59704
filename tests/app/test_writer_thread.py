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
from sqlalchemy import event

from app.db import WRITE_OPTION, Database, WriterThread
from tests.conftest import Lab

REQUEST_ID: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="none")


def test_a_robots_writes_take_turns_on_one_thread_on_sqlite_only(lab: Lab) -> None:
    """Prompts and answers write on SQLite's writer thread; the station state is a read and goes
    to the thread pool, as everything does on PostgreSQL."""
    begun: list[tuple[str, bool]] = []

    def note(conn: Any) -> None:
        write = bool(conn.get_execution_options().get(WRITE_OPTION, False))
        begun.append((threading.current_thread().name, write))

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
    """As with anyio's worker threads (run_in_threadpool): work that has begun is not abandoned,
    and a caller cancelled through its cancel scope (a request's task group) is let go only once
    the work has ended, so the admission slot it holds is held exactly as long as the work runs."""
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


def test_stop_lets_queued_work_finish_and_a_later_run_starts_a_new_thread() -> None:
    writer = WriterThread()
    names: list[str] = []

    def unit() -> None:
        time.sleep(0.01)
        names.append(threading.current_thread().name)

    async def queue_three() -> None:
        await asyncio.gather(*(writer.run(unit) for _ in range(3)))

    asyncio.run(queue_three())
    writer.stop()
    assert len(names) == 3 and len(set(names)) == 1
    first_thread = names[0]
    assert not any(t.name == first_thread for t in threading.enumerate())
    asyncio.run(writer.run(unit))
    writer.stop()
    assert len(names) == 4


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
