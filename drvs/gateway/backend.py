"""What the gateway needs of DRVS, as an interface: the ROS glue (:mod:`drvs.ros.gateway`)
implements it as a ROS client of DRVS, the unit tests with a fake. Every call returns within its
own deadline (or raises :class:`NoServer`); the cached views never block.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from drvs.gateway.body import DetectBody, WatchBody

__all__ = ['Ack', 'Drvs', 'NoServer']


class NoServer(Exception):
    """No DRVS server answered a call within its deadline; the message says what failed."""


@dataclass(frozen=True)
class Ack:
    """DRVS's acknowledgement of a request or watch (docs/interface.md, "Services")."""

    status: int
    message: str = ''
    vision_systems: int = 0
    retry_after: float = 0.0
    period: float = 0.0
    duration: float = 0.0


class Drvs(Protocol):
    """DRVS as the gateway sees it. The blocking calls run on the gateway's worker threads; the
    callbacks of requests and watches reach :meth:`drvs.gateway.app.Gateway.deliver`."""

    def detect(self, body: DetectBody, request_id: str) -> Ack:
        """DetectObjectBoundary with the gateway's callback service. :raises NoServer:"""

    def watch(self, body: WatchBody, request_id: str, duration: float) -> Ack:
        """WatchObjectBoundary (``duration`` 0 withdraws). :raises NoServer:"""

    def registry(self) -> list[dict[str, Any]] | None:
        """The newest ``/drvs/registry``: ``[{"name", "provider", "field_of_view", "algorithms"}]``;
        None before the first."""

    def objects(self) -> dict[str, Any] | None:
        """The newest ``/drvs/objects``: ``{"stamp", "algorithms", "objects"}``; None before the first."""

    def robots(self) -> dict[str, dict[str, Any]]:
        """The robots heard: name -> ``{"status": {...}, "path": [[x, y], ...]}`` (the floor-plan
        page); each value is replaced, never changed in place, when a message comes."""

    def diagnostics(self) -> list[dict[str, Any]]:
        """The newest ``/diagnostics`` status of each DRVS node: ``{"name", "level", "message",
        "hardware_id", "values", "age"}``."""
