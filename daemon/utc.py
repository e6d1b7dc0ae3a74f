"""Calendar time for the records the daemon keeps (manifests, event logs, scan folder names).

The only place the runtime reads the wall clock: scheduling runs on the event loop's clock,
which tests replace with virtual time.
"""

from __future__ import annotations

from datetime import UTC, datetime


def utc_now() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


def utc_stamp() -> str:
    """The current time as an ISO 8601 UTC string (what manifests and event lines record)."""
    return utc_now().isoformat()
