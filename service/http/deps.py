"""Dependencies of the routes (FastAPI ``Depends``): what a request may use, in one place.

The application keeps its sessions, model registry and settings on ``app.state`` (set by the
lifespan in service/http/app.py); routes never look there themselves but declare what they need.
They are ``async``: FastAPI runs a plain ``def`` dependency in its thread pool, a hand-off per
dependency per request for what is an attribute read (measured: 321 -> 158 us of the ASGI app per
chunk request).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from ..models.cache import Registry
from ..models.jobs import Jobs
from ..problems import Problem
from ..sessions.manager import Sessions
from ..settings import Settings


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_sessions(request: Request) -> Sessions:
    return sessions_of(request.scope)


async def get_registry(sessions: Annotated[Sessions, Depends(get_sessions)]) -> Registry:
    return sessions.registry


async def get_jobs(request: Request) -> Jobs:
    return request.app.state.jobs


def tenant_of(scope) -> str | None:
    """The tenant a request (or a WebSocket) authenticated as (service/http/tenants.py stores it in the
    scope's state); None when the server has no tenants file (every session is then everyone's)."""
    tenant = (scope.get("state") or {}).get("tenant")
    if tenant is None and getattr(scope["app"].state, "tenants", None) is not None:  # never without the guard
        raise Problem(401, "this server needs a tenant's token: send Authorization: Bearer TOKEN",
                      "Authorization", headers={"WWW-Authenticate": 'Bearer realm="yauyau"'})
    return tenant


def sessions_of(scope) -> Sessions:
    """The worker's sessions (503 while the lifespan has not made them)."""
    sessions = getattr(scope["app"].state, "sessions", None)
    if sessions is None:
        raise Problem(503, "models are still loading")
    return sessions


async def get_tenant(request: Request) -> str | None:
    return tenant_of(request.scope)


async def require_admin(request: Request, tenant: Annotated[str | None, Depends(get_tenant)]) -> None:
    """403 unless the tenant is an admin (admin = true in the tenants file); anyone without tenants."""
    tenants = getattr(request.app.state, "tenants", None)
    if tenants is not None and not tenants.is_admin(tenant):
        raise Problem(403, f"tenant {tenant!r} may not do this: precomputing models and reading their jobs "
                           "needs an admin tenant (admin = true in the tenants file)", "Authorization")


SettingsDep = Annotated[Settings, Depends(get_settings)]
JobsDep = Annotated[Jobs, Depends(get_jobs)]
SessionsDep = Annotated[Sessions, Depends(get_sessions)]
RegistryDep = Annotated[Registry, Depends(get_registry)]
TenantDep = Annotated[str | None, Depends(get_tenant)]
AdminOnly = [Depends(require_admin)]
