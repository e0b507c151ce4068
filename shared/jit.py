"""How the project's compiled kernels are built: the numba flags, in one place.

Every kernel is cached on disk (compiled once per machine, not per process). Two arithmetic
settings exist, both deterministic: a kernel's result does not depend on how its input is chunked,
and two kernels that do the same operations in the same order agree bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from numba import njit

F = TypeVar("F", bound=Callable)


def kernel(fn: F) -> F:
    """Compile ``fn`` with IEEE arithmetic exactly as written (no fast-math): it returns the bits
    numpy returns for the same operations in the same order."""
    return njit(cache=True)(fn)


def fma_kernel(fn: F) -> F:
    """Compile ``fn`` allowing fused multiply–add and nothing else: no reassociation, so every
    sample is still computed by the same operations in the same order whatever the chunking."""
    return njit(cache=True, fastmath={"contract"})(fn)
