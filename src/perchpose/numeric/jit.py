"""Compiled inner loops: ``compiled`` turns a function of numbers and numpy arrays into machine
code with numba (on its first call, cached on disk beside the module for the next process).

The fits' inner loops (the blurred-step edge model, the printed-pattern model) touch each
pixel a few times per Gauss-Newton round; written as numpy expressions they spend most of
their time making small temporary arrays. Compiled, the same loops run over the pixels once.
``NUMBA_DISABLE_JIT=1`` in the environment runs them as plain Python (slowly): for a debugger
or a coverage tool. ``KERNELS`` lists them all, so that ``perchpose.warmup`` can check that it
built every one before a live source's first frame.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba

F = TypeVar("F", bound=Callable[..., object])

KERNELS: list[Any] = []  # every kernel ``compiled`` made, in import order (numba dispatchers)


def compiled(function: F) -> F:
    """``function`` compiled to machine code (no Python objects inside: numbers, numpy arrays
    and tuples of them), releasing the GIL, cached on disk. A division by zero gives an
    infinity or NaN, as in numpy, rather than raising (Python's rule puts a test of the
    divisor before every division: the edge fit took 7 % longer); the fits check their
    results for finite values."""
    kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(function)
    KERNELS.append(kernel)
    return cast(F, kernel)


def uncompiled() -> list[str]:
    """The kernels imported so far that have no machine code yet (their qualified names): the
    ones whose first call would compile, or load from the disk cache, mid-run."""
    return [f"{k.py_func.__module__}.{k.py_func.__qualname__}" for k in KERNELS if not k.signatures]
