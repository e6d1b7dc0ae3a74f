"""The application's shared objects (aiohttp AppKeys)."""

from __future__ import annotations

import asyncio
from typing import Any

from aiohttp import web

ACCESS: web.AppKey[Any] = web.AppKey("access", object)
SERVICE: web.AppKey[Any] = web.AppKey("service", object)
LIBRARY: web.AppKey[Any] = web.AppKey("library", object)
CARRIERS: web.AppKey[Any] = web.AppKey("carriers", object)
CLOSING: web.AppKey[asyncio.Event] = web.AppKey("closing", asyncio.Event)
