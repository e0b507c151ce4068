"""``driveby fleet``'s entry (the CLI dispatches ``driveby <package> ...`` to ``<package>.node.main``)."""

from .fleet import main

__all__ = ["main"]
