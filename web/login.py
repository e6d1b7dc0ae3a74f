"""``/login`` and ``/logout``: the operator token exchanged for a session cookie.

Bound beyond loopback, readers log in once with the token (web/access.py); the cookie is
HttpOnly (no script reads it), SameSite=Strict (no other site's page sends it) and holds an
HMAC of the token, never the token.
"""

from __future__ import annotations

import hmac

from aiohttp import web

from web import keys
from web.access import SESSION_COOKIE, Access, safe_next, session_value

MAX_TOKEN_CHARS = 512


def _form(message: str, target: str, status: int = 200) -> web.Response:
    from html import escape

    page = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Log in · tbp-rig</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="stylesheet" href="/static/style.css"></head>
<body><header><span class="brand">tbp-rig</span></header>
<main><form class="card login" method="post" action="/login">
<h1>Log in</h1>
<p class="muted">This rig shows scans only to people with the operator token.</p>
<input type="hidden" name="next" value="{escape(target)}">
<label>Operator token <input type="password" name="token" id="token" autocomplete="current-password" autofocus></label>
<button class="primary" type="submit" id="login">Log in</button>
<p class="error" id="message">{escape(message)}</p>
</form></main></body></html>"""
    return web.Response(text=page, content_type="text/html", status=status,
                        headers={"Cache-Control": "no-store"})


async def login_page(request: web.Request) -> web.Response:
    return _form("", safe_next(request.query.get("next")))


async def login(request: web.Request) -> web.Response:
    access: Access = request.app[keys.ACCESS]
    form = await request.post()
    target = safe_next(str(form.get("next", "/")))
    given = str(form.get("token", ""))[:MAX_TOKEN_CHARS].strip()
    if access.token is None:
        return _form("This server has no operator token: nothing to log in to.", target, status=404)
    if not given or not hmac.compare_digest(session_value(given), session_value(access.token)):
        return _form("That is not the operator token.", target, status=401)
    response = web.HTTPSeeOther(target)
    response.set_cookie(SESSION_COOKIE, session_value(given), httponly=True, samesite="Strict", path="/")
    raise response


async def logout(request: web.Request) -> web.Response:
    response = web.HTTPSeeOther("/login")
    response.del_cookie(SESSION_COOKIE, path="/")
    raise response


def routes(app: web.Application) -> None:
    app.router.add_get("/login", login_page)
    app.router.add_post("/login", login)
    app.router.add_post("/logout", logout)
