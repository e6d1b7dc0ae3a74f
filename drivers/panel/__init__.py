"""The operator panel: start/stop buttons, e-stop state, status LED and subject lights over serial."""

from drivers.panel.errors import (
    PanelCommandRefused,
    PanelDisconnected,
    PanelError,
    PanelHeartbeatLost,
    PanelProtocolError,
    PanelStateError,
    PanelTimeout,
)
from drivers.panel.panel import LinkState, OperatorPanel, PanelEvent
from drivers.panel.protocol import StatusLed
from drivers.panel.serial_link import open_serial

__all__ = [
    "LinkState",
    "OperatorPanel",
    "PanelCommandRefused",
    "PanelDisconnected",
    "PanelError",
    "PanelEvent",
    "PanelHeartbeatLost",
    "PanelProtocolError",
    "PanelStateError",
    "PanelTimeout",
    "StatusLed",
    "open_serial",
]
