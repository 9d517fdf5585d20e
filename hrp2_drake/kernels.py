"""numba kernels: each step's per-tick arithmetic, compiled, written once.

A step (`hrp2_drake.step.Step`) keeps its state arrays and calls its kernel; both of
its shells (its LeafSystem and the fused controller) call the same kernel, so no numpy
twin of the arithmetic remains. The rules (../shared/CONVENTIONS.md, "numba"):

- `@kernel` is `numba.njit(cache=True)`: no fastmath (it changes results). Elementwise
  code gives numpy's numbers bit for bit; a reduction (a dot product, a sum) may round
  differently from BLAS: the step that has one says where and by how much.
- Pass few arrays (each array argument costs about 80 ns): constants packed once, at
  construction, into one or two arrays.
- A step calls its kernels by their module-level names (never a dispatcher kept on
  `self`), so that `interpreted()` can swap them for their Python source.
- Compile before the loop: `Step.warm_up()` calls each of the step's kernels once on
  arrays of the real types and layouts, without changing the step's state; then
  `freeze()` disables compiling, so that a call with a new signature raises instead of
  compiling for tens of seconds inside a real-time loop; `thaw()` allows it again.

With `NUMBA_DISABLE_JIT=1` in the environment (before numba is imported) every kernel
is its Python source. `interpreted()` does the same for the kernels of this process,
within a block: what the tests compare the compiled kernels with.

The cache: numba writes compiled kernels beside their module, in `__pycache__` (an
editable install: the source tree; CI: the clone's, fresh each run, so CI compiles
once per run); where that folder is not writable (a system-wide install), in
`$NUMBA_CACHE_DIR` if set, else numba's user cache folder (`~/.cache/numba` on Linux).
"""

import contextlib
import sys
from collections.abc import Callable, Iterator

import numba

#: Every kernel of the package: (module name, attribute name, dispatcher).
_KERNELS: list[tuple[str, str, Callable]] = []
#: Whether compiling is disabled (`freeze`).
_frozen = False


def kernel(function: Callable) -> Callable:
    """`numba.njit(cache=True)` for a step's per-tick arithmetic (module docstring);
    registers it under its module and name."""
    dispatcher = numba.njit(cache=True)(function)
    _KERNELS.append((function.__module__, function.__name__, dispatcher))
    return dispatcher


def kernels() -> list[Callable]:
    """Every registered kernel's dispatcher."""
    return [dispatcher for _, _, dispatcher in _KERNELS]


def jit_enabled() -> bool:
    """Whether kernels are compiled (numba's jit not disabled by NUMBA_DISABLE_JIT)."""
    return not numba.config.DISABLE_JIT


def freeze() -> None:
    """No more compiling: a kernel called with a signature it has not compiled for
    raises (numba's TypeError) instead of compiling; one never compiled (a step the
    controller does not have) raises at any call."""
    global _frozen
    if jit_enabled():
        for dispatcher in kernels():
            if dispatcher.signatures:
                dispatcher.disable_compile()
            else:  # numba's disable_compile() asserts a compiled signature
                dispatcher._can_compile = False
    _frozen = True


def thaw() -> None:
    """Compiling allowed again (after `freeze`)."""
    global _frozen
    if jit_enabled():
        for dispatcher in kernels():
            dispatcher.disable_compile(False)
    _frozen = False


def frozen() -> bool:
    return _frozen


@contextlib.contextmanager
def compile_disabled() -> Iterator[None]:
    """`freeze()` within the block, `thaw()` after it."""
    freeze()
    try:
        yield
    finally:
        thaw()


@contextlib.contextmanager
def interpreted() -> Iterator[None]:
    """Within the block every registered kernel, called by its module-level name, is
    its Python source (what NUMBA_DISABLE_JIT gives a whole process)."""
    swapped = []
    for module_name, name, dispatcher in _KERNELS:
        module = sys.modules[module_name]
        if (
            getattr(module, name) is dispatcher
        ):  # (with NUMBA_DISABLE_JIT: the function)
            setattr(module, name, getattr(dispatcher, "py_func", dispatcher))
            swapped.append((module, name, dispatcher))
    try:
        yield
    finally:
        for module, name, dispatcher in swapped:
            setattr(module, name, dispatcher)
