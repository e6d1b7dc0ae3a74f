"""Errors that cross a process boundary intact.

Planning and TSDF fusion may run in a worker process; an error raised there is pickled back.
Python rebuilds an exception as ``cls(*args)``, which fails for errors whose ``__init__`` takes
their own fields (``TooFewFrames(usable, needed, per_camera)``) and not the message. These
rebuild from their message and fields instead, so the daemon sees the same typed error, with
the same attributes, as in-process code would.
"""

from __future__ import annotations

from typing import Any


def _rebuild(cls: type[BaseException], args: tuple[Any, ...], state: dict[str, Any]) -> BaseException:
    error = cls.__new__(cls, *args)
    error.args = args
    error.__dict__.update(state)
    return error


class PicklableError(Exception):
    """Mixin base: pickles as (class, message args, attributes), never calling ``__init__``."""

    def __reduce__(self) -> tuple[Any, ...]:
        return _rebuild, (type(self), self.args, dict(self.__dict__))
