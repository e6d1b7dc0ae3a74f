"""Associations with a DICOM peer (daemon/clinic/dimse.py) against a peer written here byte by byte:
what it answers is named, whatever the peer does with the connection after answering."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from daemon.clinic.dimse import AssociationRejected, PeerUnreachable, associate
from daemon.clinic.site import Peer

WORKLIST_FIND = "1.2.840.10008.5.1.4.31"
EXPLICIT_LE = "1.2.840.10008.1.2.1"


def rejection_pdu(result: int, source: int, reason: int) -> bytes:
    """A-ASSOCIATE-RJ (PS3.8 9.3.4): type 0x03, reserved, length 4, reserved, result, source, reason."""
    return struct.pack(">BBIBBBB", 0x03, 0, 4, 0, result, source, reason)


@contextmanager
def rejecting_peer(answer: bytes, associations: int) -> Iterator[int]:
    """A peer on loopback that reads each association request, answers ``answer`` (or nothing,
    when empty) and closes at once."""
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve() -> None:
        for _ in range(associations):
            connection, _ = server.accept()
            with connection:
                header = connection.recv(6, socket.MSG_WAITALL)
                length = struct.unpack(">I", header[2:6])[0]
                connection.recv(length, socket.MSG_WAITALL)
                if answer:
                    connection.sendall(answer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield port
    finally:
        server.close()
        thread.join(timeout=10)


@pytest.fixture
def descheduled_requester(monkeypatch: pytest.MonkeyPatch) -> None:
    """The requesting thread pauses after sending its request (a loaded machine), so the peer's
    answer and its close come before it looks at the connection again."""
    from pynetdicom.acse import ACSE

    send_request = ACSE.send_request

    def send_and_pause(self) -> None:
        send_request(self)
        time.sleep(0.3)

    monkeypatch.setattr(ACSE, "send_request", send_and_pause)


def test_a_rejection_is_named_even_when_the_close_is_seen_first(descheduled_requester):
    """pynetdicom reports a failed connection when the close comes before it looks (the CI saw
    "unreachable" for dcmtk's worklist provider rejecting an unknown called AE title)."""
    with rejecting_peer(rejection_pdu(0x01, 0x01, 0x07), 1) as port:
        peer = Peer(host="127.0.0.1", port=port, called_aet="NOTRISWL")
        with pytest.raises(AssociationRejected) as rejected:
            associate("TBPRIG1", peer, [(WORKLIST_FIND, [EXPLICIT_LE])], timeout_s=5.0)
    assert "Called AE title not recognised" in str(rejected.value) and not rejected.value.retry


def test_a_peer_that_rejects_and_closes_at_once_is_named_as_rejecting_every_time():
    tries = 20
    with rejecting_peer(rejection_pdu(0x01, 0x01, 0x07), tries) as port:
        peer = Peer(host="127.0.0.1", port=port, called_aet="NOTRISWL")
        for _ in range(tries):
            with pytest.raises(AssociationRejected) as rejected:
                associate("TBPRIG1", peer, [(WORKLIST_FIND, [EXPLICIT_LE])], timeout_s=5.0)
            assert "Called AE title not recognised" in str(rejected.value) and not rejected.value.retry


def test_a_transient_rejection_is_retried_later():
    with rejecting_peer(rejection_pdu(0x02, 0x03, 0x02), 1) as port:
        with pytest.raises(AssociationRejected, match="Transient") as rejected:
            associate("TBPRIG1", Peer(host="127.0.0.1", port=port, called_aet="RISWL"),
                      [(WORKLIST_FIND, [EXPLICIT_LE])], timeout_s=5.0)
    assert rejected.value.retry


def test_a_peer_that_closes_without_answering_is_unreachable():
    with rejecting_peer(b"", 1) as port:
        with pytest.raises(PeerUnreachable, match="no association"):
            associate("TBPRIG1", Peer(host="127.0.0.1", port=port, called_aet="RISWL"),
                      [(WORKLIST_FIND, [EXPLICIT_LE])], timeout_s=5.0)


def test_requests_are_sent_without_waiting_for_the_peers_delayed_ack():
    """An established association writes with TCP_NODELAY: with Nagle's algorithm each DIMSE
    request's last segment waits for the peer's delayed ACK (about 40 ms a C-STORE)."""
    from pynetdicom import AE

    verification = "1.2.840.10008.1.1"
    scp = AE(ae_title="PACS")
    scp.add_supported_context(verification, [EXPLICIT_LE])
    server = scp.start_server(("127.0.0.1", 0), block=False)
    try:
        port = server.server_address[1]
        assoc = associate("TBPRIG1", Peer(host="127.0.0.1", port=port, called_aet="PACS"),
                          [(verification, [EXPLICIT_LE])], timeout_s=5.0)
        try:
            assert assoc.dul.socket.socket.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
            assert int(assoc.send_c_echo().Status) == 0
        finally:
            assoc.release()
    finally:
        server.shutdown()
