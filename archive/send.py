"""Sending a study to the archive: C-STORE over one association (pynetdicom), or STOW-RS
(DICOMweb over HTTP, multipart/related of application/dicom parts) in batches.

Each instance is made, sent and confirmed one at a time (C-STORE) or a batch at a time (STOW-RS);
``on_sent`` hears of every instance the archive confirmed, so a queue records progress as it
goes and a transfer cut off resumes after the last confirmed instance. Failures are the typed
errors of daemon/clinic/dimse.py, naming the peer and the reason.
"""

from __future__ import annotations

import io
import json
import ssl
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from archive.instances import Instance, study_file
from daemon.clinic.dimse import (
    ContextsRefused,
    PeerUnreachable,
    StatusRefused,
    TransferAborted,
    associate,
    check_status,
)
from daemon.clinic.site import Peer, Tls

STOW_BATCH = 16
"""Instances per STOW-RS request (a 40-megapixel JPEG is about 10 MB)."""


@dataclass
class SendResult:
    sent: list[str] = field(default_factory=list)
    """SOP Instance UIDs confirmed by the archive, in order."""
    skipped: int = 0
    """Instances not sent again: confirmed by an earlier attempt."""


def send_dimse(instances: Sequence[Instance], ae_title: str, peer: Peer, *, tls: Tls | None = None,
               done: frozenset[str] = frozenset(), on_sent: Callable[[Instance], None] | None = None) -> SendResult:
    """C-STORE every instance not in ``done`` over one association to ``peer``."""
    result = SendResult(skipped=sum(i.sop_instance_uid in done for i in instances))
    todo = [i for i in instances if i.sop_instance_uid not in done]
    if not todo:
        return result
    contexts: dict[str, set[str]] = {}
    for instance in todo:
        contexts.setdefault(instance.sop_class_uid, set()).add(instance.transfer_syntax)
    assoc = associate(ae_title, peer, [(c, sorted(s)) for c, s in contexts.items()], tls=tls)
    try:
        for instance in todo:
            dataset = study_file(instance)
            try:
                status = assoc.send_c_store(dataset)
            except RuntimeError as exc:  # pynetdicom: the association ended (aborted, cut) before the request
                if assoc.is_established:
                    raise
                raise TransferAborted(peer, f"association ended before {instance.kind} {instance.name}") from exc
            check_status(peer, status, f"C-STORE of {instance.kind} {instance.name}")
            result.sent.append(instance.sop_instance_uid)
            if on_sent is not None:
                on_sent(instance)
    finally:
        if assoc.is_established:
            assoc.release()
    return result


def _part(instance: Instance) -> bytes:
    from pydicom.filewriter import dcmwrite

    buffer = io.BytesIO()
    dcmwrite(buffer, study_file(instance), enforce_file_format=True)
    return buffer.getvalue()


def send_stow(instances: Sequence[Instance], url: str, study_uid: str, *, tls: Tls | None = None,
              done: frozenset[str] = frozenset(), on_sent: Callable[[Instance], None] | None = None,
              timeout_s: float = 120.0) -> SendResult:
    """STOW-RS every instance not in ``done`` to ``url``/studies/``study_uid``, STOW_BATCH a request."""
    result = SendResult(skipped=sum(i.sop_instance_uid in done for i in instances))
    todo = [i for i in instances if i.sop_instance_uid not in done]
    context = tls.context() if tls is not None else None
    for start in range(0, len(todo), STOW_BATCH):
        batch = todo[start:start + STOW_BATCH]
        boundary = uuid.uuid4().hex
        body = io.BytesIO()
        for instance in batch:
            body.write(f"--{boundary}\r\nContent-Type: application/dicom\r\n\r\n".encode())
            body.write(_part(instance))
            body.write(b"\r\n")
        body.write(f"--{boundary}--\r\n".encode())
        answer = _post(f"{url}/studies/{study_uid}", body.getvalue(), boundary, context, timeout_s)
        failed = answer.get("00081198", {}).get("Value", []) if isinstance(answer, dict) else []
        if failed:
            reason = failed[0].get("00081197", {}).get("Value", ["?"])[0]
            uid = failed[0].get("00081155", {}).get("Value", ["?"])[0]
            raise StatusRefused(url, f"STOW-RS refused instance {uid}: failure reason {reason} "
                                     f"({len(failed)} of {len(batch)} in the request)")
        for instance in batch:
            result.sent.append(instance.sop_instance_uid)
            if on_sent is not None:
                on_sent(instance)
    return result


def _post(url: str, body: bytes, boundary: str, context: ssl.SSLContext | None, timeout_s: float) -> object:
    request = urllib.request.Request(url, data=body, method="POST", headers={
        "Content-Type": f'multipart/related; type="application/dicom"; boundary={boundary}',
        "Accept": "application/dicom+json"})
    try:
        with urllib.request.urlopen(request, timeout=timeout_s, context=context) as response:
            text = response.read()
    except urllib.error.HTTPError as exc:
        detail = exc.read()[:300].decode(errors="replace").strip()
        error = ContextsRefused if exc.code in (400, 406, 415) else StatusRefused
        raise error(url, f"HTTP {exc.code} {exc.reason}" + (f": {detail}" if detail else "")) from exc
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise PeerUnreachable(url, f"no answer: {reason}") from exc
    try:
        return json.loads(text) if text.strip() else {}
    except ValueError:
        return {}
