"""The rig's browser side: the dermatologist's scan viewer and the operator's console, served
by the daemon (aiohttp, in the daemon's event loop)."""
