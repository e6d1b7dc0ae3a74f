"""Who may read and change what through the web server.

Reading (the viewer, the console's status and events) shows patients' images. While the
server is bound to loopback, whoever is on the rig PC may read. Bound beyond loopback, every
page and API request needs a login with the operator token (``POST /login`` sets an HttpOnly,
SameSite=Strict session cookie derived from the token), unless the daemon was started with
``--http-open-reads``, an explicit choice to show scans to the whole network. The static
assets (styles, scripts, three.js) hold no patient data and are served to anyone.

Changing anything (START, ABORT, RESET, lesion marks) needs, on every request:

* a JSON body (``Content-Type: application/json``): a page of another origin cannot send one
  without a CORS preflight, which this server never grants;
* no foreign ``Origin`` header (the browser names the page that sent the request);
* the bearer token (``Authorization: Bearer ...``) or the login's session cookie when a
  token is configured; without a token, only a client on the same machine, and only while
  the server is bound to loopback.

While bound to loopback, the ``Host`` header must name the loopback address too, so a
page on another site cannot rebind its DNS name to 127.0.0.1 and read the store.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlencode

from aiohttp import web

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]", "::1")


class AccessError(ValueError):
    """The web server's access settings are unusable (a bad address or token file)."""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def parse_listen(text: str) -> tuple[str, int]:
    """"HOST:PORT" (IPv6 in brackets) -> (host, port); AccessError naming the text otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise AccessError(f"--http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8470")
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not 0 <= number <= 65535:
        raise AccessError(f"--http {text!r}: port {port!r} must be 0..65535")
    return host.strip("[]"), number


def read_token(path: Path) -> str:
    """The write token from a file (first line); AccessError if missing, unreadable or short."""
    try:
        token = path.read_text().strip()
    except OSError as exc:
        raise AccessError(f"--http-token-file {path}: {exc.strerror or exc}") from None
    if len(token) < 16:
        raise AccessError(f"--http-token-file {path}: the token has {len(token)} characters, needs 16 or more")
    return token


SESSION_COOKIE = "tbp_session"
PUBLIC_PREFIXES = ("/login", "/logout", "/static/", "/vendor/three/")
"""Paths served without a login: the login itself and assets without patient data."""


def session_value(token: str) -> str:
    """The session cookie's value for a token: an HMAC, so the cookie never holds the token itself."""
    return hmac.new(token.encode(), b"tbp-rig web session v1", hashlib.sha256).hexdigest()


def safe_next(target: str | None) -> str:
    """Where a login returns to: a path on this server only (no scheme, host or '//')."""
    if not target or not target.startswith("/") or target.startswith("//") or "\\" in target:
        return "/"
    return target


@dataclass(frozen=True)
class Access:
    """The write policy. host/port: where the server listens; token: None for none."""

    host: str
    port: int
    token: str | None = None
    open_reads: bool = False

    def __post_init__(self) -> None:
        if not self.loopback and self.token is None and not self.open_reads:
            raise AccessError(
                f"--http {self.host}:{self.port} listens beyond this machine and would show patients' "
                "images to the network: give --http-token-file (a login for every reader) or, "
                "deliberately, --http-open-reads")

    @property
    def loopback(self) -> bool:
        return is_loopback(self.host)

    @property
    def login_required(self) -> bool:
        """Reads need a login: bound beyond loopback without --http-open-reads."""
        return not self.loopback and not self.open_reads

    def logged_in(self, request: web.Request) -> bool:
        """The request carries the token as a bearer header or the login's session cookie."""
        if self.token is None:
            return False
        cookie = request.cookies.get(SESSION_COOKIE, "")
        if cookie and hmac.compare_digest(cookie.encode(), session_value(self.token).encode()):
            return True
        scheme, _, value = request.headers.get("Authorization", "").partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(value.strip().encode(), self.token.encode())

    def check_read(self, request: web.Request) -> None:
        """Raise the response that sends a reader without a login to it (pages) or refuses (API)."""
        if not self.login_required or request.path.startswith(PUBLIC_PREFIXES) or self.logged_in(request):
            return
        if request.path.startswith("/api/"):
            raise web.HTTPUnauthorized(text="log in first: this server shows scans only after a login (/login)",
                                       headers={"WWW-Authenticate": 'Bearer realm="tbp-rig"'})
        raise web.HTTPSeeOther(f"/login?{urlencode({'next': request.path_qs})}")

    @property
    def writes_enabled(self) -> bool:
        return self.token is not None or self.loopback

    def check_host(self, request: web.Request) -> None:
        """On a loopback binding, refuse a Host header that names anything else (DNS rebinding)."""
        if not self.loopback:
            return
        name = request.host.rsplit(":", 1)[0] if not request.host.endswith("]") else request.host
        if name not in LOOPBACK_NAMES:
            raise web.HTTPMisdirectedRequest(
                text=f"this server answers only to the loopback address, not to Host {request.host!r}")

    def check_write(self, request: web.Request) -> None:
        """Raise the 4xx that refuses a write request, or return when it may proceed."""
        origin = request.headers.get("Origin")
        if origin is not None and origin not in self._own_origins(request):
            raise web.HTTPForbidden(text=f"cross-origin write from {origin!r} refused")
        if request.content_type != "application/json":
            raise web.HTTPUnsupportedMediaType(
                text=f"writes take a JSON body (Content-Type: application/json), not {request.content_type!r}")
        if self.token is not None:
            if not self.logged_in(request):
                raise web.HTTPUnauthorized(text="this action needs the operator token (Authorization: Bearer ...)",
                                           headers={"WWW-Authenticate": 'Bearer realm="tbp-rig"'})
            return
        if not self.loopback:
            raise web.HTTPForbidden(text="changes are disabled: the server listens beyond this machine "
                                         "without a token (start the daemon with --http-token-file)")
        peer = request.remote or ""
        if not is_loopback(peer):
            raise web.HTTPForbidden(text=f"changes only from this machine without a token, not from {peer!r}")

    def _own_origins(self, request: web.Request) -> set[str]:
        return {f"{request.scheme}://{request.host}"}
