"""numba's ``njit``, paid for only when a kernel is worth compiling.

The package's inner loops (``model/_kernels.py``, ``model/discretise.py``,
``monitor/_kernel.py``, ``identify/grid.py``, ``envs/_kernels.py``) are plain Python written in
the subset numba compiles. Importing numba and loading the first compiled function from its
on-disk cache costs about 0.6 s of CPU on the project's 2-core machine (0.25 s import, 0.35 s
for LLVM's start-up on the first call), far more than a 2-s recording
takes to simulate in the interpreter. So ``@njit`` here records the function and compiles
nothing:

- calling a :class:`Kernel` runs numba's compiled code, compiling (or loading from cache) its
  module on the first call, exactly as ``numba.njit`` did (in mode ``never``, its source in the
  interpreter);
- :func:`pick` lets a caller that knows the size of its job run small jobs in the interpreter
  instead (the same source, the same arithmetic: results agree to rounding), until the process
  has spent :data:`INTERPRETED_BUDGET` robot-steps there; after that, or once numba is loaded
  for any kernel anyway, it returns the compiled code.

``MECANUM_HIL_JIT=always`` compiles every job, ``never`` interprets every job (slow on large
ones), ``auto`` (default) as above. :func:`forced` sets the mode for this process only.

The size of numba's thread pool is set here too: :func:`kernel_threads` for a process that
shares the cores with a helper, :func:`few_threads` for jobs too small to wake the pool.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Callable
from typing import Any

#: Robot-steps (sub-steps) a process may run interpreted before :func:`pick` compiles: about
#: 0.3 s of the simulator in the interpreter (25 us per robot-step on the linear path),
#: half of what loading numba costs; a 10-s recording at 1 kHz still runs without numba.
INTERPRETED_BUDGET = 12_000

#: ``prange`` for the interpreter; a compiled module gets numba's.
prange = range

_lock = threading.RLock()
_state = threading.local()
_compiled_modules: set[str] = set()
_spent = 0
_forced: str | None = None


def mode() -> str:
    """``MECANUM_HIL_JIT``: ``always``, ``never`` or ``auto`` (the default, also for others);
    inside :func:`forced`, its mode."""
    if _forced is not None:
        return _forced
    value = os.environ.get("MECANUM_HIL_JIT", "auto").strip().lower()
    return value if value in ("always", "never", "auto") else "auto"


@contextlib.contextmanager
def forced(how: str):
    """This process (every thread) in mode ``how`` inside, whatever ``MECANUM_HIL_JIT`` says;
    child processes still get the environment's. For a process that hands its compiled work
    to another one and keeps only small jobs: ``forced("never")`` keeps numba out of it.
    Kernels already compiled in this process stay compiled."""
    global _forced
    if how not in ("always", "never", "auto"):
        raise ValueError(f"mode must be always, never or auto, got {how!r}")
    before = _forced
    _forced = how
    try:
        yield
    finally:
        _forced = before


class Kernel:
    """A function numba compiles when it is first called compiled.

    Attributes
    ----------
    py_func : callable
        The Python function (numba's name for it).
    options : dict
        ``numba.njit`` options (``cache``, ``parallel``, ``inline`` ...).
    """

    def __init__(self, func: Callable, options: dict[str, Any]) -> None:
        self.py_func = func
        self.options = options
        self.__name__ = func.__name__
        self.__qualname__ = func.__qualname__
        self.__module__ = func.__module__
        self.__doc__ = func.__doc__
        self.__wrapped__ = func
        self._dispatcher = None

    def __call__(self, *args):
        disp = self._dispatcher
        if disp is not None:
            return disp(*args)
        if getattr(_state, "interpreting", False) or mode() == "never":
            return self.py_func(*args)
        return self.compiled()(*args)

    def compiled(self):
        """numba's dispatcher for this function (its module compiled or loaded from cache)."""
        if self._dispatcher is None:
            _compile_module(self.__module__)
        return self._dispatcher

    def __repr__(self) -> str:
        state = "compiled" if self._dispatcher is not None else "not compiled"
        return f"<Kernel {self.__module__}.{self.__qualname__} ({state})>"


def njit(*args, **options):
    """``numba.njit`` without numba: ``@njit`` or ``@njit(cache=True, ...)``."""
    if args and callable(args[0]) and not options:
        return Kernel(args[0], {})
    return lambda func: Kernel(func, options)


def _compile_module(name: str) -> None:
    """Replace every kernel in module ``name`` (and the modules it calls into) by numba's."""
    with _lock:
        if name in _compiled_modules:
            return
        import numba

        module = sys.modules[name]
        names = vars(module)
        # kernels imported from other modules first: numba resolves globals at compile time
        for key, value in list(names.items()):
            if isinstance(value, Kernel) and value.__module__ != name:
                setattr(module, key, value.compiled())
        if names.get("prange") is range:
            module.prange = numba.prange
        own = [(k, v) for k, v in names.items() if isinstance(v, Kernel) and v.__module__ == name]
        for key, kernel in own:
            kernel._dispatcher = numba.njit(**kernel.options)(kernel.py_func)
            setattr(module, key, kernel._dispatcher)
        _compiled_modules.add(name)


def is_compiled(module: str) -> bool:
    """Whether the kernels of ``module`` (a dotted name) are numba's by now: then a helper of
    theirs costs nothing more to run compiled."""
    return module in _compiled_modules


def load_compiled(module: str) -> None:
    """Make the kernels of ``module`` (a dotted name) numba's now (numba imported; each is
    compiled, or loaded from numba's cache, on its first call): from then on every job of the
    process runs compiled (:func:`interpret` says no once a module is), unless
    ``MECANUM_HIL_JIT=never``.

    For a long computation whose result should not depend on what the process did before:
    the interpreter's arithmetic equals numba's only to rounding, and a search that starts on
    one and goes on with the other can end in another local minimum than one run on numba's
    throughout (``diagnose``: a recording diagnosed after others in one process came out
    otherwise than alone).
    """
    if mode() == "never":
        return
    import importlib

    importlib.import_module(module)
    _compile_module(module)


@contextlib.contextmanager
def kernel_threads(count: int):
    """Run numba's parallel kernels on at most ``count`` threads in the calling thread inside
    (restored after): for a process that shares the cores with others working beside it (a
    diagnosis and its helper, a core each), where a kernel's second thread would only wait
    for the core the other process holds. Nothing while numba is not loaded."""
    numba = sys.modules.get("numba")
    before = numba.get_num_threads() if numba is not None else None
    if before is None or before <= count:
        yield
        return
    numba.set_num_threads(count)
    try:
        yield
    finally:
        numba.set_num_threads(before)


@contextlib.contextmanager
def few_threads(work: float):
    """Run numba's parallel loops on one thread when the work is small.

    ``work`` is roughly the number of wheel-steps to simulate (robots x samples x 4). Waking a
    thread pool costs more than a few thousand steps take, and on a loaded machine a parallel
    launch waits for the busiest core, so small batches (a Jacobian) run faster serially.
    """
    numba = sys.modules.get("numba")
    if numba is None or work >= 200_000:
        # numba not loaded: the job runs interpreted (mecanum_hil._jit), or compiles now and
        # pays far more for loading numba than its threads could cost
        yield
        return
    before = numba.get_num_threads()
    if before == 1:  # already (beside a helper: mecanum_hil._jit.kernel_threads)
        yield
        return
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)


def compiled(kernel) -> Callable:
    """numba's dispatcher for ``kernel`` (a :class:`Kernel`, or a module global that already is
    the dispatcher: compiling a module replaces its kernels by numba's)."""
    return kernel.compiled() if isinstance(kernel, Kernel) else kernel


def _interpreted(kernel: Kernel) -> Callable:
    def run(*args):
        before = getattr(_state, "interpreting", False)
        _state.interpreting = True
        try:
            return kernel.py_func(*args)
        finally:
            _state.interpreting = before
    return run


def interpret(units: int) -> bool:
    """Whether a job costing ``units`` of :data:`INTERPRETED_BUDGET` runs without numba.

    True (and the budget charged) while the process's interpreted work stays within the budget
    and no kernel module is compiled yet; False once numba is loaded or the budget would be
    exceeded (or as ``MECANUM_HIL_JIT`` says). :func:`pick` decides with it, and so do numpy
    paths that stand in for a kernel on small jobs (``mecanum_hil.model.linear``).
    """
    global _spent
    how = mode()
    # once numba is loaded for any kernel, another costs only its cache (tens of milliseconds)
    if how == "always" or (_compiled_modules and how != "never"):
        return False
    with _lock:
        if how == "never" or _spent + units <= INTERPRETED_BUDGET:
            _spent += units
            return True
    return False


def pick(kernel: Kernel, robot_steps: int) -> Callable:
    """The kernel to run a job of ``robot_steps`` (robots x samples x sub-steps) with.

    The interpreter while the process's interpreted work stays within
    :data:`INTERPRETED_BUDGET` and no kernel module is compiled yet; numba's compiled code
    otherwise (or as ``MECANUM_HIL_JIT`` says): see :func:`interpret`.
    """
    if not isinstance(kernel, Kernel):  # a module global already replaced by numba's dispatcher
        return kernel
    if kernel._dispatcher is None and interpret(robot_steps):
        return _interpreted(kernel)
    return kernel.compiled()
