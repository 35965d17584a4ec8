"""Who may use the admin endpoints: the holder of the replica's admin token.

Scripts send it as ``Authorization: Bearer <token>`` (every admin endpoint).
A browser cannot send that header from a typed URL, so the read-only views
(``/fleet``, ``/fleet.json``) also take it once as ``?token=<token>``: the
fleet page then answers with a cookie and a redirect to itself without the
query, so the token does not stay in the address bar, the history or a
bookmark. The cookie holds not the token but an HMAC of a fixed label under it:
it opens the read-only views only (never ``DELETE /sessions``), every worker of
the replica computes the same one, and changing the token revokes it. Every
comparison is constant-time (``hmac.compare_digest``).
"""

from __future__ import annotations

import hashlib
import hmac

from fastapi import HTTPException, Request

__all__ = ["AdminAuth", "VIEW_COOKIE"]

#: The cookie the read-only admin views accept (``AdminAuth.view_cookie``).
VIEW_COOKIE = "walkstream_view"

_VIEW_LABEL = b"walkstream read-only admin views"


class AdminAuth:
    """token : the replica's admin token; None or empty: the admin endpoints are off (403)."""

    def __init__(self, token: str | None) -> None:
        self.token = token or None

    def _enabled(self) -> str:
        if not self.token:
            raise HTTPException(403, "admin endpoints are disabled: start the server with --admin-token TOKEN "
                                     "(or WALKSTREAM_ADMIN_TOKEN) to enable them")
        return self.token

    def _bearer(self, request: Request, token: str) -> bool:
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        return scheme.lower() == "bearer" and hmac.compare_digest(given.strip().encode(), token.encode())

    def require(self, request: Request) -> None:
        """The Bearer header, for every admin endpoint (a FastAPI dependency)."""
        token = self._enabled()
        if not self._bearer(request, token):
            raise HTTPException(401, "a valid 'Authorization: Bearer <admin token>' header is required",
                                headers={"WWW-Authenticate": "Bearer"})

    def require_view(self, request: Request) -> None:
        """The Bearer header, ``?token=`` or the view cookie, for the read-only views (a FastAPI dependency)."""
        token = self._enabled()
        if self._bearer(request, token) or self.query_ok(request):
            return
        cookie = request.cookies.get(VIEW_COOKIE, "")
        if not hmac.compare_digest(cookie.encode(), self.view_cookie().encode()):
            raise HTTPException(401, "the admin token is required: an 'Authorization: Bearer <admin token>' "
                                     "header, or open the page once as ?token=<admin token>",
                                headers={"WWW-Authenticate": "Bearer"})

    def query_ok(self, request: Request) -> bool:
        """Whether the request carries the admin token as ``?token=``."""
        given = request.query_params.get("token")
        return bool(self.token) and given is not None and hmac.compare_digest(given.encode(), self.token.encode())

    def view_cookie(self) -> str:
        """The view cookie's value: an HMAC-SHA256 of a fixed label under the token (hex)."""
        return hmac.new(self._enabled().encode(), _VIEW_LABEL, hashlib.sha256).hexdigest()

    def peer_headers(self) -> dict:
        """Headers for asking the replica's other workers on a caller's behalf (already let in here)."""
        return {"authorization": f"Bearer {self.token}"} if self.token else {}
