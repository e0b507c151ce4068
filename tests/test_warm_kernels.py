"""The kernel warm-up's list (tests/kernel_signatures.txt) names kernels that exist, with signatures
numba reads back: a renamed or removed kernel shows here, not as a silently slower suite."""

from __future__ import annotations

import importlib

from numba.core.registry import CPUDispatcher

from tests.warm_kernels import SIGNATURES, parse_signature


def test_every_listed_signature_names_a_kernel_and_parses():
    lines = SIGNATURES.read_text().splitlines()
    assert lines and len(set(lines)) == len(lines)
    for line in lines:
        module, name, text = line.split(" ", 2)
        kernel = getattr(importlib.import_module(module), name, None)
        assert isinstance(kernel, CPUDispatcher), line
        sig = parse_signature(text)
        assert isinstance(sig, tuple) and len(sig) == kernel.py_func.__code__.co_argcount, line
