"""The one small interface between the aggregator and every estimator."""

from __future__ import annotations

from typing import Any, Protocol

from shared.schema import ApSegment


class Estimator(Protocol):
    """``update`` adds a segment's information, ``retract`` removes exactly what ``update`` added
    (a superseded segment), ``snapshot`` returns the current estimate as plain data.

    Optional: ``accepts(segment)``, whether the estimator takes a segment, a function of its route
    and grid spacing alone (the aggregator remembers the answer per pair).
    """

    def update(self, segment: ApSegment) -> None: ...

    def retract(self, segment: ApSegment) -> None: ...

    def snapshot(self) -> Any: ...
