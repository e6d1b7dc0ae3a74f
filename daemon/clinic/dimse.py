"""Associations with the clinic's DICOM peers (pynetdicom), and their failures as typed errors that
name the peer and the reason: unreachable, association rejected (with the peer's result, source
and reason), no presentation context accepted, aborted or cut mid-transfer, a refused status.

pynetdicom's own log records stay at WARNING and above: its debug and info records can print
datasets, and a dataset holds the patient's name.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Sequence
from typing import Any

from daemon.clinic.site import Peer, Tls
from daemon.errors import DaemonError

logging.getLogger("pynetdicom").setLevel(logging.WARNING)


class DicomPeerError(DaemonError):
    """A DICOM peer could not be used; ``retry``: whether trying again later may succeed (an outage,
    an abort) or not without someone changing a configuration (a rejected AE title, an unknown SOP
    class)."""

    retry = True

    def __init__(self, peer: object, reason: str) -> None:
        self.peer = str(peer)
        self.reason = reason
        super().__init__(f"{self.peer}: {reason}")


class PeerUnreachable(DicomPeerError):
    """No TCP connection (refused, timed out, no route) or no answer to the association request."""


class AssociationRejected(DicomPeerError):
    """The peer rejected the association (A-ASSOCIATE-RJ): the reason is the peer's."""

    def __init__(self, peer: object, reason: str, *, permanent: bool) -> None:
        super().__init__(peer, reason)
        self.retry = not permanent


class ContextsRefused(DicomPeerError):
    """The peer accepted the association but none, or not all, of the SOP classes and transfer
    syntaxes asked for."""

    retry = False


class TransferAborted(DicomPeerError):
    """The association was aborted or the connection cut while requests were in flight."""


class StatusRefused(DicomPeerError):
    """The peer answered a request with a failure status (out of resources, cannot understand)."""


def associate(ae_title: str, peer: Peer, contexts: Sequence[tuple[str, Sequence[str]]], *,
              tls: Tls | None = None, timeout_s: float = 30.0) -> Any:
    """An established pynetdicom association to ``peer`` for ``contexts`` ((SOP class UID,
    transfer syntaxes) each). Raises PeerUnreachable, AssociationRejected or ContextsRefused."""
    from pynetdicom import AE, evt
    from pynetdicom.events import EventHandlerType
    from pynetdicom.pdu import A_ASSOCIATE_RJ

    ae = AE(ae_title=ae_title)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = timeout_s
    ae.connection_timeout = timeout_s
    for sop_class, syntaxes in contexts:
        ae.add_requested_context(sop_class, list(syntaxes))
    tls_args = None if tls is None else (tls.context(), peer.host)
    # The peer's A-ASSOCIATE-RJ is kept as it arrives (pynetdicom's reactor thread): when the
    # rejection and the close it brings come before the requesting thread looks at the connection,
    # pynetdicom reports a failed connection and aborts, with no answer kept.
    rejections: list[Any] = []
    handlers: list[EventHandlerType] = [(evt.EVT_PDU_RECV, lambda event: rejections.append(event.pdu)
                 if isinstance(event.pdu, A_ASSOCIATE_RJ) else None)]
    assoc = ae.associate(peer.host, peer.port, ae_title=peer.called_aet, tls_args=tls_args, evt_handlers=handlers)
    if assoc.is_established:
        refused = [cx.abstract_syntax for cx in assoc.rejected_contexts]
        if refused:
            assoc.release()
            raise ContextsRefused(peer, f"the peer does not accept SOP class {refused[0]} (of {len(refused)} refused)")
        # A DIMSE request is written as a few PDUs and then its response awaited: with Nagle's
        # algorithm the request's last segment waits for the peer's delayed ACK (about 40 ms a
        # request on Linux, most of an image's C-STORE on loopback).
        transport = assoc.dul.socket
        if transport is None or transport.socket is None:  # closed since it was established
            assoc.abort()
            raise TransferAborted(peer, "the connection closed as the association was established")
        transport.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return assoc
    answer = getattr(assoc.acceptor, "primitive", None)
    rejection = rejections[0] if rejections else answer if assoc.is_rejected else None
    if rejection is not None:
        raise AssociationRejected(
            peer, f"association rejected ({rejection.result_str}, by the {rejection.source_str}): "
                  f"{rejection.reason_str}", permanent=rejection.result == 0x01)
    if answer is not None and not assoc.accepted_contexts:
        raise ContextsRefused(peer, "the peer accepted none of the SOP classes and transfer syntaxes asked for")
    raise PeerUnreachable(peer, "no association: connection refused, timed out, or no answer to the request")


def check_status(peer: Peer, status: Any, what: str) -> int:
    """The status code of a DIMSE response; TransferAborted when none came (aborted, cut),
    StatusRefused for a failure."""
    if status is None or "Status" not in status:
        raise TransferAborted(peer, f"{what}: no response (association aborted or connection cut)")
    code = int(status.Status)
    if code in (0x0000, 0xFF00, 0xFF01) or 0xB000 <= code <= 0xBFFF:
        return code
    comment = str(status.get("ErrorComment", "") or "").strip()
    raise StatusRefused(peer, f"{what}: status 0x{code:04X}" + (f" ({comment[:120]})" if comment else ""))
