"""The capture agent's JSON-lines protocol (docs/capture-agent-protocol.md), both directions.

Each line is one UTF-8 JSON object ending in "\\n" (strict JSON: no NaN or Infinity, at most
MAX_NESTING deep). Requests carry an integer ``id`` and an
``op``; the answer carries the same ``id`` and ``ok``: true with the op's fields, or false with
``error: {code, message}``. The host (drivers/phone/camera.py) and the simulated agent
(drivers/sim/phone.py) both use these parsers, so a malformed line is a typed
:class:`AgentProtocolError` on either side.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from typing import Any

from drivers.phone.errors import AgentProtocolError

PROTOCOL_VERSION = 1
SOCKET_NAME = "tbp-capture"
AGENT_CLASS = "com.tbp.CaptureAgent"
AGENT_PATH = "/data/local/tmp/tbp-capture-agent.jar"
READY_PREFIX = "TBP-CAPTURE-AGENT READY"
MAX_LINE = 64 * 1024
MAX_NESTING = 256  # arrays and objects inside each other, as the agent's parser allows
OPS = ("hello", "focus", "capture", "clock", "delete")

ERROR_CODES = (
    "BAD_REQUEST", "UNKNOWN_OP", "CAMERA_BUSY", "CAMERA_ERROR", "FOCUS_OUT_OF_RANGE", "FOCUS_TIMEOUT",
    "CAPTURE_FAILED", "STORAGE_FULL", "NOT_FOUND",
)


@dataclass(frozen=True)
class AgentRequest:
    id: int
    op: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class AgentResponse:
    """ok True: fields holds the op's answer; ok False: code and message say why."""

    id: int
    ok: bool
    fields: dict[str, Any] = field(default_factory=dict)
    code: str = ""
    message: str = ""

    def number(self, name: str, *, device: str = "agent", integer: bool = False) -> float | int:
        """A required finite number field (an int when integer=True)."""
        value = self.fields.get(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                (integer and not isinstance(value, int)) or not math.isfinite(value):
            kind = "an integer" if integer else "a number"
            raise AgentProtocolError(device, "answer", f"field {name!r} must be {kind}, got {value!r}")
        return value

    def text(self, name: str, *, device: str = "agent") -> str:
        value = self.fields.get(name)
        if not isinstance(value, str) or not value:
            raise AgentProtocolError(device, "answer", f"field {name!r} must be a non-empty string, got {value!r}")
        return value


def _load(line: bytes | str, device: str, side: str) -> dict[str, Any]:
    if isinstance(line, bytes):
        if len(line) > MAX_LINE:
            raise AgentProtocolError(device, side, f"line of {len(line)} bytes > {MAX_LINE}")
        try:
            line = line.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise AgentProtocolError(device, side, f"line is not UTF-8: {exc}") from None
    if not line.endswith("\n"):
        raise AgentProtocolError(device, side, f"line not terminated by a newline: {line[:80]!r}")
    if _nesting(line) > MAX_NESTING:
        raise AgentProtocolError(device, side, f"JSON nested deeper than {MAX_NESTING}")
    try:
        obj = json.loads(line, parse_constant=_no_constant)
    except (ValueError, RecursionError) as exc:
        raise AgentProtocolError(device, side, f"not JSON ({exc}): {line[:80]!r}") from None
    if not isinstance(obj, dict):
        raise AgentProtocolError(device, side, f"line is a JSON {type(obj).__name__}, not an object")
    ident = obj.get("id")
    if isinstance(ident, bool) or not isinstance(ident, int) or not 0 <= ident < 2**53:
        raise AgentProtocolError(device, side, f"'id' must be a non-negative integer, got {ident!r}")
    return obj


_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def _nesting(text: str) -> int:
    """How deep arrays and objects nest in a JSON text (brackets inside strings do not count)."""
    deepest = depth = 0
    for char in _STRING.sub("", text):
        if char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not JSON")


def encode_request(request_id: int, op: str, **params: Any) -> bytes:
    """One request line."""
    if op not in OPS:
        raise ValueError(f"unknown agent op {op!r} (known: {', '.join(OPS)})")
    return (json.dumps({"id": request_id, "op": op, **params}, separators=(",", ":")) + "\n").encode()


def parse_request(line: bytes | str, *, device: str = "agent") -> AgentRequest:
    """Parse a request line (the agent's side); AgentProtocolError when malformed."""
    obj = _load(line, device, "request")
    op = obj.pop("op", None)
    ident = obj.pop("id")
    if not isinstance(op, str):
        raise AgentProtocolError(device, "request", f"'op' must be a string, got {op!r}")
    return AgentRequest(ident, op, obj)


def encode_result(request_id: int, **fields: Any) -> bytes:
    """A success answer line."""
    return (json.dumps({"id": request_id, "ok": True, **fields}, separators=(",", ":")) + "\n").encode()


def encode_error(request_id: int, code: str, message: str) -> bytes:
    """An error answer line."""
    return (json.dumps({"id": request_id, "ok": False, "error": {"code": code, "message": message}},
                       separators=(",", ":")) + "\n").encode()


def parse_response(line: bytes | str, *, device: str = "agent") -> AgentResponse:
    """Parse an answer line (the host's side); AgentProtocolError when malformed."""
    obj = _load(line, device, "answer")
    ident, ok = obj.pop("id"), obj.pop("ok", None)
    if not isinstance(ok, bool):
        raise AgentProtocolError(device, "answer", f"'ok' must be true or false, got {ok!r}")
    if ok:
        return AgentResponse(ident, True, obj)
    error = obj.get("error")
    if not isinstance(error, dict) or not isinstance(error.get("code"), str) or \
            not isinstance(error.get("message", ""), str):
        raise AgentProtocolError(device, "answer", f"error answer without error.code/message: {error!r}")
    return AgentResponse(ident, False, {}, error["code"], error.get("message", ""))
