"""Tenants: who may use the API, and from which host names (one ASGI middleware, :class:`TenantGuard`).

``YAUYAU_TENANTS_FILE`` (``yauyau serve --tenants FILE``) names a TOML file of ``[[tenant]]`` tables::

    [[tenant]]
    name = "alice"
    token_sha256 = "<64 hex digits: printf %s TOKEN | sha256sum>"
    admin = true          # optional: may precompute models (POST /v1/models) and read jobs

The file holds hashes, never tokens.  With it, every request except the open routes (health, metrics,
the API description) needs ``Authorization: Bearer TOKEN``; the token is hashed with SHA-256 and
compared with every tenant's hash by :func:`hmac.compare_digest` (no early exit: the time taken does
not depend on which tenant, if any, matched).  The tenant's name goes into
``scope["state"]["tenant"]``, where the routes (service/http/deps.py) and the rate limits read it; a
session belongs to the tenant that created it (service/sessions/manager.py).

Without a tenants file nobody is authenticated, so ``yauyau serve`` listens on loopback only unless
``--insecure-bind`` says that something in front authenticates (:func:`serve_notes`).

Every request, tenants or not, must name this server in its ``Host`` header (DNS rebinding: a page
of another site whose name was re-pointed at 127.0.0.1 would otherwise read the API through the
user's browser): ``YAUYAU_ALLOWED_HOSTS``, by default the loopback names and the bind address.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from yauyau.solver.errors import InputError

from ..problems import problem_response

REALM = 'Bearer realm="yauyau"'
# open to anyone: probes, metrics scrapers and the description of the API (it holds no data)
OPEN_PATHS = frozenset({"/livez", "/readyz", "/metrics", "/docs", "/docs/oauth2-redirect", "/redoc",
                        "/openapi.json"})
# answered whatever the Host: load balancers probe by IP address, and these say only "ok" / why not
ANY_HOST_PATHS = frozenset({"/livez", "/readyz"})
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}")
_HEX64 = re.compile(r"[0-9a-fA-F]{64}")
_VIEW = re.compile(r"/v1/sessions/[^/]+/view")
_KEYS = {"name", "token_sha256", "admin"}


@dataclass(frozen=True)
class Tenant:
    name: str
    digest: bytes  # SHA-256 of the bearer token
    admin: bool = False


class Tenants:
    """The tenants of a tenants file: who a bearer token is, and who is an admin."""

    def __init__(self, tenants: list[Tenant], source: str = ""):
        self.tenants = tuple(tenants)
        self.source = source
        self._admin = {t.name: t.admin for t in tenants}

    def match(self, token: bytes) -> Tenant | None:
        """The tenant whose hash is the token's SHA-256, or None; compared with every tenant, in
        constant time each, whatever matches."""
        digest = hashlib.sha256(token).digest()
        found = None
        for tenant in self.tenants:
            if hmac.compare_digest(digest, tenant.digest):
                found = tenant
        return found

    def is_admin(self, name: str | None) -> bool:
        return bool(self._admin.get(name or "", False))


def load_tenants(path: str | Path | None) -> Tenants | None:
    """The tenants of ``path`` (None when no file is set); InputError naming the file, the tenant and
    the field when the file is unreadable, not TOML, or a tenant is incomplete or repeated."""
    if path is None or str(path) == "":
        return None
    where = f"tenants file {path}"
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError("tenants_file", f"cannot read the {where}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError("tenants_file", f"the {where} is not valid TOML: {exc}") from None
    extra = sorted(set(data) - {"tenant"})
    if extra:
        raise InputError("tenants_file", f"{where}: unknown key {extra[0]!r} (the file holds [[tenant]] "
                                         "tables only)")
    tables = data.get("tenant")
    if not isinstance(tables, list) or not tables:
        raise InputError("tenants_file", f"{where}: no [[tenant]] table (each needs name and token_sha256)")
    tenants: list[Tenant] = []
    for index, table in enumerate(tables):
        tenants.append(_tenant(table, index, where))
    _no_repeats(tenants, where)
    return Tenants(tenants, str(path))


def _tenant(table: Any, index: int, where: str) -> Tenant:
    label = f"[[tenant]] #{index + 1}"
    if not isinstance(table, dict):
        raise InputError("tenants_file", f"{where}: {label} is not a table")
    name = table.get("name")
    if isinstance(name, str) and _NAME.fullmatch(name):
        label = f"tenant {name!r}"

    def bad(field: str, why: str) -> InputError:
        return InputError("tenants_file", f"{where}: {label}: {field}: {why}")

    if "token" in table:
        raise bad("token", "the file never holds a token: give token_sha256, the SHA-256 of the token in "
                           "hex (printf %s TOKEN | sha256sum)")
    unknown = sorted(set(table) - _KEYS)
    if unknown:
        raise bad(unknown[0], "unknown key (a tenant has name, token_sha256 and optional admin)")
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise bad("name", "required: 1 to 64 letters, digits and _.@- (starting with a letter or digit), "
                          f"got {name!r}")
    digest = table.get("token_sha256")
    if not isinstance(digest, str) or not _HEX64.fullmatch(digest):
        shown = "missing" if digest is None else f"{len(digest)} characters" if isinstance(digest, str) \
            else type(digest).__name__
        raise bad("token_sha256", f"must be 64 hexadecimal digits, the SHA-256 of the token "
                                  f"(printf %s TOKEN | sha256sum), got {shown}")
    admin = table.get("admin", False)
    if not isinstance(admin, bool):
        raise bad("admin", f"must be true or false, got {admin!r}")
    return Tenant(name, bytes.fromhex(digest), admin)


def _no_repeats(tenants: list[Tenant], where: str) -> None:
    names: set[str] = set()
    owners: dict[bytes, str] = {}
    for tenant in tenants:
        if tenant.name in names:
            raise InputError("tenants_file", f"{where}: tenant {tenant.name!r}: name: given twice")
        if tenant.digest in owners:
            raise InputError("tenants_file", f"{where}: tenant {tenant.name!r}: token_sha256: the same as "
                                             f"tenant {owners[tenant.digest]!r}'s (each tenant needs its "
                                             "own token)")
        names.add(tenant.name)
        owners[tenant.digest] = tenant.name


# -- host names --------------------------------------------------------------------------------
def host_name(value: str) -> str:
    """The host part of a Host header or of a configured name: no port, no IPv6 brackets, lower case,
    no trailing dot ('[::1]:8000' -> '::1', 'Example.org.:80' -> 'example.org')."""
    value = value.strip()
    if value.startswith("["):
        end = value.find("]")
        value = value[1:end] if end > 0 else value[1:]
    elif value.count(":") == 1:
        value = value.split(":", 1)[0]
    return value.lower().rstrip(".")


def allowed_hosts(settings: Any) -> frozenset[str] | None:
    """The host names requests may carry (None: any): ``allowed_hosts`` when set, else the loopback
    names and the bind address."""
    given = settings.allowed_hosts
    if given is None or not given.strip():
        return frozenset({*LOOPBACK_NAMES, host_name(settings.host)})
    names = [name.strip() for name in given.split(",") if name.strip()]
    if "*" in names:
        return None
    return frozenset(host_name(name) for name in names)


def is_loopback(host: str) -> bool:
    name = host_name(host)
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def serve_notes(settings: Any) -> list[str]:
    """What ``yauyau serve`` checks before it listens: the tenants file loads, and without one the
    server binds loopback only unless ``insecure_bind``; InputError (exit 2) otherwise.  Returns the
    lines to print at start (that there is no authentication; that a wildcard bind with the default
    host names answers loopback names only)."""
    notes = []
    if settings.tenants_file is None:
        if not is_loopback(settings.host) and not settings.insecure_bind:
            raise InputError("host", f"refusing to listen on {settings.host} without authentication (no "
                                     "tenants file): anyone who reaches the port could read, inject into "
                                     "and delete every session. Give --tenants FILE (YAUYAU_TENANTS_FILE) "
                                     "so that every /v1 request needs a bearer token, or pass "
                                     "--insecure-bind (YAUYAU_INSECURE_BIND=true) when a proxy or firewall "
                                     "in front authenticates")
        notes.append(f"yauyau serve: running WITHOUT authentication (no tenants file): every client that "
                     f"reaches {settings.host}:{settings.port} may use every session; give --tenants FILE "
                     "to require bearer tokens")
    else:
        tenants = load_tenants(settings.tenants_file)
        admins = sum(t.admin for t in tenants.tenants)
        notes.append(f"yauyau serve: {len(tenants.tenants)} tenant(s) ({admins} admin) from "
                     f"{settings.tenants_file}: /v1 requests need Authorization: Bearer TOKEN")
    if settings.allowed_hosts is None and not is_loopback(settings.host):
        notes.append(f"yauyau serve: requests must name localhost, 127.0.0.1, ::1 or {settings.host} in "
                     "their Host header; set --allowed-hosts (YAUYAU_ALLOWED_HOSTS) to the names clients use")
    return notes


# -- the middleware ----------------------------------------------------------------------------
class TenantGuard:
    """Pure ASGI middleware: the Host header must be an allowed name (400 problem+json naming
    ``Host``; /livez and /readyz answer any Host), then, with tenants, a bearer token must name a
    tenant (401 problem+json with ``WWW-Authenticate``; the open paths need none).  Stores the
    tenant's name in ``scope["state"]["tenant"]``.  A browser opening a live page without a token
    gets the page itself with 401, so that it can ask for the token."""

    def __init__(self, app, tenants: Tenants | None = None, hosts: frozenset[str] | None = None):
        self.app = app
        self.tenants = tenants
        self.hosts = hosts

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):  # a WebSocket is guarded as a request is
            return await self.app(scope, receive, send)
        path = scope.get("path", "")
        if self.hosts is not None and path not in ANY_HOST_PATHS:
            host = _header(scope, b"host")
            if host is None or host_name(host.decode("latin-1")) not in self.hosts:
                return await _bad_host(host, scope, receive, send)
        if self.tenants is None or path in OPEN_PATHS:
            return await self.app(scope, receive, send)
        token = _bearer(_header(scope, b"authorization"))
        tenant = self.tenants.match(token) if token is not None else None
        if tenant is None:
            return await self._unauthorized(token is not None, scope, receive, send)
        scope.setdefault("state", {})["tenant"] = tenant.name
        return await self.app(scope, receive, send)

    async def _unauthorized(self, wrong: bool, scope, receive, send) -> None:
        challenge = REALM + (', error="invalid_token"' if wrong else "")
        if _VIEW.fullmatch(scope.get("path", "")) and scope.get("method") in ("GET", "HEAD") \
                and b"text/html" in (_header(scope, b"accept") or b""):
            from .live import live_response

            response = live_response(401, {"WWW-Authenticate": challenge})
        else:
            detail = ("the bearer token is not a tenant's: send Authorization: Bearer TOKEN with a token "
                      "whose SHA-256 is in the tenants file" if wrong else
                      "this server needs a tenant's token: send Authorization: Bearer TOKEN")
            response = problem_response(401, detail, "Authorization", instance=scope.get("path"),
                                        headers={"WWW-Authenticate": challenge})
        await response(scope, receive, send)


def _header(scope, name: bytes) -> bytes | None:
    for key, value in scope.get("headers") or ():
        if key == name:
            return value
    return None


def _bearer(value: bytes | None) -> bytes | None:
    """The token of ``Bearer TOKEN`` (the scheme in any case), else None."""
    if value is None:
        return None
    scheme, _, token = value.strip().partition(b" ")
    token = token.strip()
    return token if scheme.lower() == b"bearer" and token else None


async def _bad_host(host: bytes | None, scope, receive, send) -> None:
    shown = "none" if host is None else repr(host.decode("latin-1")[:100])
    detail = (f"Host {shown} is not a name of this server (a guard against DNS rebinding): use the name the "
              "server is configured with, or add it to YAUYAU_ALLOWED_HOSTS (--allowed-hosts; * allows any)")
    response = problem_response(400, detail, "Host", instance=scope.get("path"))
    await response(scope, receive, send)
