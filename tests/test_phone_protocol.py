"""The capture agent's JSON-lines protocol: round trips and typed errors for malformed lines."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.phone import protocol
from drivers.phone.errors import AgentProtocolError

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**40, 2**40) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=10,
)


def test_request_bytes_exact() -> None:
    assert protocol.encode_request(7, "focus", diopters=2.5) == b'{"id":7,"op":"focus","diopters":2.5}\n'
    assert protocol.encode_request(1, "hello", version=1) == b'{"id":1,"op":"hello","version":1}\n'
    with pytest.raises(ValueError, match="unknown agent op"):
        protocol.encode_request(1, "reboot")


@settings(deadline=None)
@given(st.integers(0, 2**53 - 1), st.sampled_from(protocol.OPS),
       st.dictionaries(st.text(min_size=1, max_size=8).filter(lambda k: k not in ("id", "op")), json_values,
                       max_size=4))
def test_request_round_trip(ident: int, op: str, params: dict) -> None:
    request = protocol.parse_request(protocol.encode_request(ident, op, **params))
    assert (request.id, request.op, request.params) == (ident, op, params)


@settings(deadline=None)
@given(st.integers(0, 2**53 - 1), st.dictionaries(st.sampled_from(["path", "size", "device_ns"]), json_values))
def test_result_round_trip(ident: int, fields: dict) -> None:
    answer = protocol.parse_response(protocol.encode_result(ident, **fields))
    assert answer.ok and answer.id == ident and answer.fields == fields


def test_error_round_trip() -> None:
    answer = protocol.parse_response(protocol.encode_error(3, "CAPTURE_FAILED", "HAL error"))
    assert (answer.ok, answer.id, answer.code, answer.message) == (False, 3, "CAPTURE_FAILED", "HAL error")


@settings(deadline=None)
@given(st.binary(max_size=200))
def test_random_bytes_give_typed_errors(raw: bytes) -> None:
    for parse in (protocol.parse_response, protocol.parse_request):
        try:
            parse(raw + b"\n")
        except AgentProtocolError:
            pass


@settings(deadline=None)
@given(json_values)
def test_json_without_valid_id_or_ok_is_refused(value: object) -> None:
    line = json.dumps(value) + "\n"
    if isinstance(value, dict) and isinstance(value.get("id"), int) and not isinstance(value.get("id"), bool) \
            and value["id"] >= 0 and isinstance(value.get("ok"), bool) and value.get("ok"):
        protocol.parse_response(line)
        return
    if isinstance(value, dict) and value.get("ok") is False and isinstance(value.get("id"), int) \
            and isinstance(value.get("error"), dict) and isinstance(value["error"].get("code"), str):
        return
    with pytest.raises(AgentProtocolError):
        protocol.parse_response(line)


@pytest.mark.parametrize("line, problem", [
    (b'{"id":1,"ok":true}', "newline"),
    (b'{"id":1,"ok":true\n', "not JSON"),
    (b'[1,2]\n', "not an object"),
    (b'{"id":-1,"ok":true}\n', "'id'"),
    (b'{"id":"1","ok":true}\n', "'id'"),
    (b'{"id":1,"ok":"yes"}\n', "'ok'"),
    (b'{"id":1,"ok":false}\n', "error.code"),
    (b'{"id":1,"ok":false,"error":{"message":"x"}}\n', "error.code"),
    (b'\xff\xfe\n', "UTF-8"),
])
def test_malformed_answers(line: bytes, problem: str) -> None:
    with pytest.raises(AgentProtocolError, match=problem):
        protocol.parse_response(line, device="PHONE7")


def test_typed_field_access() -> None:
    answer = protocol.parse_response(b'{"id":1,"ok":true,"size":12,"exposure_s":0.002,"path":"/a","bad":true}\n')
    assert answer.number("size", integer=True) == 12
    assert answer.number("exposure_s") == 0.002
    assert answer.text("path") == "/a"
    with pytest.raises(AgentProtocolError, match="'exposure_s' must be an integer"):
        answer.number("exposure_s", integer=True)
    with pytest.raises(AgentProtocolError, match="'bad'"):
        answer.number("bad")
    with pytest.raises(AgentProtocolError, match="'missing'"):
        answer.text("missing")
    with pytest.raises(AgentProtocolError, match="'op'"):
        protocol.parse_request(b'{"id":1}\n')
    with pytest.raises(AgentProtocolError, match="bytes >"):
        protocol.parse_response(b"{" + b" " * protocol.MAX_LINE + b"}\n")
