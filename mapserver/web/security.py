"""Who may change what robots navigate on: the review token, the operator's session cookie and
the forms' CSRF tokens, and the address rule.

- The token is the content of ``web.token_file`` (whitespace stripped), compared in constant
  time. Without a token file the review actions are off.
- API clients send ``Authorization: Bearer <token>``. A person signs in once with the token and
  a name (for the change's history); the session cookie holds the name, a random id and an HMAC
  of both under the token (HttpOnly, SameSite=Strict): nothing is stored on the server.
- Every form that changes something carries a CSRF token, an HMAC of the session id: a page
  of another site cannot forge it (and SameSite=Strict keeps the cookie from its requests).
- Binding to an address other than the loopback without a token is refused at start.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import re
import secrets
import time
from dataclasses import dataclass
from pathlib import Path

from mapserver.config import WebConfig
from mapserver.errors import ConfigError

COOKIE = "mapserver_session"
_NAME = re.compile(r"[A-Za-z0-9 ._@-]{1,40}")


def read_token(path: Path | None) -> str | None:
    """The review token, or None when no token file is configured."""
    if path is None:
        return None
    try:
        token = path.read_text(encoding="utf-8").strip()
    except OSError as error:
        raise ConfigError(f"cannot read the web token: {error.strerror}", file=path) from None
    if len(token) < 16:
        raise ConfigError(
            "the web token must be at least 16 characters (make one with: "
            "python3 -c 'import secrets; print(secrets.token_urlsafe(32))')",
            file=path,
        )
    return token


def is_loopback(host: str) -> bool:
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_port(listen: str) -> tuple[str, int]:
    """The host and the port of ``web.listen`` (``HOST:PORT``, an IPv6 host in brackets)."""
    host, _, port = listen.rpartition(":")
    number = int(port)
    if not 0 < number < 65536:
        raise ConfigError(f"web.listen: port {number} is not between 1 and 65535")
    return host.strip("[]"), number


def check_settings(web: WebConfig) -> None:
    """The web settings as serving them needs them, else a :class:`ConfigError`: the token
    file readable and long enough, a non-loopback address only with a token
    (:func:`check_listen`). What ``mapserver check-config`` asks too, so that a configuration
    it passes does not stop ``run``."""
    host, _ = host_port(web.listen)
    check_listen(host, read_token(web.token_file))


def check_listen(host: str, token: str | None) -> None:
    """Refuse a non-loopback address without a token: the review actions would be open."""
    if token is None and not is_loopback(host):
        raise ConfigError(
            f"refusing to serve on {host} without web.token_file: only the loopback may go "
            "without a token"
        )


def same(a: str, b: str) -> bool:
    return hmac.compare_digest(a.encode(), b.encode())


def _mac(token: str, *parts: str) -> str:
    return hmac.new(token.encode(), "\x1f".join(parts).encode(), hashlib.sha256).hexdigest()


@dataclass(frozen=True)
class Session:
    name: str
    sid: str


def valid_name(name: str) -> bool:
    # fullmatch: "$" would also match before a final newline ("Mallory\n").
    return _NAME.fullmatch(name) is not None


SESSION_HOURS = 12


def new_session_cookie(token: str, name: str, *, now: float | None = None) -> str:
    sid = secrets.token_urlsafe(16)
    issued = str(int(time.time() if now is None else now))
    return f"{sid}.{issued}.{name}.{_mac(token, 'session', sid, issued, name)}"


def read_session(
    token: str | None, cookie: str | None, *, now: float | None = None
) -> Session | None:
    """The signed-in person of a session cookie; None when it is forged, or older than
    ``SESSION_HOURS`` (sign in again)."""
    if token is None or not cookie or cookie.count(".") < 3:
        return None
    sid, issued, rest = cookie.split(".", 2)
    name, _, mac = rest.rpartition(".")
    if not valid_name(name) or not issued.isdigit():
        return None
    if not same(mac, _mac(token, "session", sid, issued, name)):
        return None
    age = (time.time() if now is None else now) - int(issued)
    if not 0 <= age <= SESSION_HOURS * 3600:
        return None
    return Session(name, sid)


def csrf_token(token: str, session: Session) -> str:
    return _mac(token, "csrf", session.sid)
