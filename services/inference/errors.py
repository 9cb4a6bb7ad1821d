"""Typed errors of the inference service. Each transport maps them to one status:

| error              | REST | gRPC               |
|--------------------|------|--------------------|
| InvalidInput       | 422  | INVALID_ARGUMENT   |
| ModuleUnavailable  | 404  | UNIMPLEMENTED      |
| Overloaded         | 429  | RESOURCE_EXHAUSTED |
| RequestTimeout     | 504  | DEADLINE_EXCEEDED  |
| NotReady           | 503  | UNAVAILABLE        |
"""

from __future__ import annotations

from core.errors import N3dmapError


class ServiceError(N3dmapError):
    """Base of the errors a request can end in on purpose (never a 500)."""


class InvalidInput(ServiceError, ValueError):
    """A request field is malformed; `field` names it (e.g. `views[0].depth`)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.reason = message


class ModuleUnavailable(ServiceError):
    """The loaded bundle lacks a module this route needs."""

    def __init__(self, route: str, missing: list[str], version: str):
        super().__init__(f"route {route!r} needs {', '.join(missing)}, which bundle {version!r} "
                         f"does not provide")
        self.route = route
        self.missing = missing


class Overloaded(ServiceError):
    """The request queue is full: retry later."""


class RequestTimeout(ServiceError):
    """The request did not finish within its deadline."""


class NotReady(ServiceError):
    """The runtime is starting or shutting down."""
