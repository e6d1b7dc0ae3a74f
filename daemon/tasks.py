"""Bounded waits for tasks: a stopped task that does not end is named, never waited for for ever,
and a cancel of the waiting task is never swallowed (``asyncio.wait`` times out with a timer,
not by cancelling)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Iterable
from typing import Any, TypeVar

import structlog

log = structlog.get_logger("daemon.tasks")

T = TypeVar("T")


async def stop_tasks(tasks: Iterable[asyncio.Task[Any]], timeout_s: float) -> list[asyncio.Task[Any]]:
    """Cancel ``tasks`` and wait up to ``timeout_s`` for them to end; returns those still running
    (left cancelled). Their results and errors count as seen. A cancel of the caller is not
    swallowed."""
    tasks = list(tasks)
    for task in tasks:
        task.cancel()
    if not tasks:
        return []
    done, pending = await asyncio.wait(tasks, timeout=timeout_s)
    for task in done:
        if not task.cancelled():
            task.exception()
    for task in pending:
        log.error("task_did_not_stop", task=describe(task), timeout_s=timeout_s)
    return list(pending)


async def settle(tasks: Iterable[asyncio.Future[Any] | None], timeout_s: float) -> list[asyncio.Future[Any]]:
    """Wait up to ``timeout_s`` for ``tasks`` to end by themselves (None entries are skipped, and
    nothing is awaited when all have ended); returns those still running. Their errors count as
    seen: the caller has its own to raise."""
    futures = [t for t in tasks if t is not None]
    running = [f for f in futures if not f.done()]
    pending: set[asyncio.Future[Any]] = set()
    if running:
        _, pending = await asyncio.wait(running, timeout=timeout_s)
    for future in futures:
        if future.done() and not future.cancelled():
            future.exception()
    return list(pending)


async def despite_cancel(work: Awaitable[T], timeout_s: float) -> T:
    """Run ``work`` to its end even when the caller is cancelled meanwhile: releasing a device (the
    depth cameras at a sweep's end) must not be cut short by a second stop arriving while the first
    unwinds. The caller's cancel is raised once ``work`` ended, or after ``timeout_s``; ``work``
    itself runs on as its own task in any case."""
    task = asyncio.ensure_future(work)
    try:
        return await asyncio.shield(task)
    except asyncio.CancelledError:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while not task.done() and loop.time() < deadline:
            try:
                await asyncio.wait([task], timeout=deadline - loop.time())
            except asyncio.CancelledError:  # one more stop: the first is raised below all the same
                continue
        if task.done() and not task.cancelled():
            task.exception()  # seen: the cancel is what the caller gets
        raise


def describe(task: asyncio.Future[Any]) -> str:
    """A task's name and the line it waits at."""
    if not isinstance(task, asyncio.Task):
        return repr(task)
    stack = task.get_stack()
    where = f" at {stack[-1].f_code.co_name} ({stack[-1].f_code.co_filename}:{stack[-1].f_lineno})" if stack else ""
    return f"{task.get_name()}{where}"
