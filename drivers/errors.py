"""What every driver's error tree shares: :class:`DeviceGone`, the device can no longer be reached.

Each driver area keeps its own tree (``PhoneError``, ``DriveError``, ``PanelError``...); the
errors meaning that the link to the device dropped or the device fell silent also derive from
:class:`DeviceGone`, so the daemon matches them by type: a phone gone from a capture is
reconnected before its retake, a drive whose link died gets a fresh link at the operator's reset.
"""

from __future__ import annotations


class DeviceGone(Exception):
    """The device's link dropped or the device fell silent: only a new connection brings it back.

    Derived from by ``PhoneDisconnected`` (and ADB's ``ConnectionLost`` below it), the motor's
    ``CanBusError`` and ``HeartbeatLost``, and the panel's ``PanelHeartbeatLost`` (its
    ``PanelDisconnected``)."""
