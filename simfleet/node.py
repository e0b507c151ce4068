"""``driveby fleet``'s entry (the CLI dispatches ``driveby <package> ...`` to ``<package>.node.main``)."""

from .fleet import build_parser, main

__all__ = ["build_parser", "main"]
