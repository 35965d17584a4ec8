"""Who may open the admin views: the Bearer header everywhere; ``?token=`` and the view cookie on the read-only
views only; nobody when the replica has no admin token."""

from __future__ import annotations

from urllib.parse import urlencode

import pytest
from fastapi import HTTPException
from starlette.requests import Request

from server.admin import VIEW_COOKIE, AdminAuth


def request(headers: dict | None = None, query: dict | None = None, cookies: dict | None = None) -> Request:
    raw = [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    if cookies:
        raw.append((b"cookie", "; ".join(f"{k}={v}" for k, v in cookies.items()).encode()))
    return Request({"type": "http", "method": "GET", "path": "/fleet", "headers": raw,
                    "query_string": urlencode(query or {}).encode()})


def refused(check, req) -> int:
    with pytest.raises(HTTPException) as exc:
        check(req)
    return exc.value.status_code


def test_the_bearer_header_opens_everything_the_query_and_cookie_only_the_views():
    auth = AdminAuth("s3cret-token")
    bearer = request({"Authorization": "Bearer s3cret-token"})
    auth.require(bearer)
    auth.require_view(bearer)
    query = request(query={"token": "s3cret-token"})
    auth.require_view(query)
    assert refused(auth.require, query) == 401
    cookie = request(cookies={VIEW_COOKIE: auth.view_cookie()})
    auth.require_view(cookie)
    assert refused(auth.require, cookie) == 401
    assert "s3cret-token" not in auth.view_cookie() and AdminAuth("other").view_cookie() != auth.view_cookie()


@pytest.mark.parametrize("req", [
    request(), request({"Authorization": "Bearer wrong"}), request({"Authorization": "Basic s3cret-token"}),
    request(query={"token": "s3cret-tokeN"}), request(cookies={VIEW_COOKIE: "s3cret-token"}),
])
def test_anything_else_is_refused_401(req):
    assert refused(AdminAuth("s3cret-token").require_view, req) == 401


def test_without_an_admin_token_the_views_are_off_403():
    auth = AdminAuth(None)
    for req in (request({"Authorization": "Bearer "}), request(query={"token": ""}), request()):
        assert refused(auth.require_view, req) == 403
        assert refused(auth.require, req) == 403
