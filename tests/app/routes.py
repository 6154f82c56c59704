"""The routes an app serves, as tests walk them (FastAPI includes routers lazily)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from fastapi import FastAPI
from fastapi.routing import APIRoute, APIWebSocketRoute, _IncludedRouter
from starlette.routing import BaseRoute, Mount


@dataclass(frozen=True)
class ServedRoute:
    """One route as served: its full path (prefixes applied), methods and the route object."""

    path: str
    methods: frozenset[str]
    websocket: bool
    route: BaseRoute


def served_routes(app: FastAPI) -> Iterator[ServedRoute]:
    """Every route of the app, included routers' routes with their prefixes."""
    for route in app.routes:
        if isinstance(route, _IncludedRouter):
            for context in route.effective_route_contexts():
                original = context.original_route
                websocket = isinstance(original, APIWebSocketRoute)
                # a WebSocket's prefixed path lives on the Starlette route it was compiled to
                path = context.path or getattr(context.starlette_route, "path", original.path)
                yield ServedRoute(path, frozenset(context.methods or ()), websocket, original)
        elif isinstance(route, Mount):
            yield ServedRoute(route.path, frozenset({"GET"}), False, route)
        else:
            methods = frozenset(getattr(route, "methods", None) or ())
            yield ServedRoute(getattr(route, "path", ""), methods, False, route)


def api_routes(app: FastAPI) -> Iterator[ServedRoute]:
    """The routes with FastAPI dependants (parameters FastAPI validates)."""
    for served in served_routes(app):
        if isinstance(served.route, APIRoute | APIWebSocketRoute):
            yield served
