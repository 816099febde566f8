"""How many threads a deltatwin process computes on, set once at start-up (docs/performance.md).

Two pools exist: the BLAS library's (numpy's and scipy's OpenBLAS), and the chunk pool of the
batched kinematics and statics (models/batched.py ``map_chunks``).  Neither helps this
package much: its matrices are 3x3 to 6x6 per point (BLAS threads only spin up and wait on
them) or a few hundred columns wide, and the chunked stages are a fraction of a command.  But
both oversubscribe the cores when commands run side by side: two processes each starting one
BLAS thread per core slowed each other by 75-240 %.  So a command uses one thread
of each unless told otherwise by ``DELTATWIN_THREADS`` (a number, or ``auto``: every core this
process may use) or an explicit ``set_threads(n)``.

Apart from the pools, a command may run one whole independent task of a few tenths of a
second or more in a second process (``models.batched.in_background``: ``diagnose``'s
attribution beside its candidates; a Jacobian's optics columns beside its pose-moving ones).
It holds no lock and spins on nothing, so beside another command it only shares the cores as
any process does: it is on when this process may use two cores or more, unless
``DELTATWIN_THREADS=1`` (or ``set_threads(1)``) asks for one core.

The same start-up sets how numpy's large arrays take their memory: in pages of 4 kB, not in
transparent huge pages (numpy asks for those on Linux, ``NUMPY_MADVISE_HUGEPAGE``).  A command
here makes its (N, 3, p) arrays once or a few times, so what costs is the first touch of new
memory, and on a machine whose kernel gathers huge pages on demand (``transparent_hugepage``
``defrag`` at ``madvise``, as on a 2-core development machine) a new huge page cost 1.3-2.0
ms per MB against 0.4 for small pages: `diagnose` of full paper-thermal spent ~0.2 s less
in the system, `fit` 0.15-0.3 s (docs/performance.md).  A ``NUMPY_MADVISE_HUGEPAGE`` already
set is the user's choice and kept.
"""
from __future__ import annotations

import os

ENVIRONMENT_VARIABLE = "DELTATWIN_THREADS"
# numpy's switch of transparent huge pages for its large arrays (read when numpy loads)
HUGEPAGE_VARIABLE = "NUMPY_MADVISE_HUGEPAGE"
# read by BLAS libraries when they load (scipy's OpenBLAS loads with scipy.linalg, later)
BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_blas_limit = None      # the threadpoolctl limiter, kept so the limit lives as long as the process


def threads_from_environment() -> int:
    """The thread count ``DELTATWIN_THREADS`` asks for (1 when unset); ValueError naming the
    variable when it is neither a positive whole number nor ``auto``."""
    raw = os.environ.get(ENVIRONMENT_VARIABLE, "").strip()
    if not raw:
        return 1
    if raw.lower() == "auto":
        from deltatwin.models.batched import usable_cores
        return usable_cores()
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"environment variable {ENVIRONMENT_VARIABLE}={raw!r}: expected a "
                         "positive whole number of threads or 'auto'")
    return n


def set_threads(threads: int | None = None) -> int:
    """Use ``threads`` (default: ``threads_from_environment()``) for both the BLAS libraries and
    the chunk pool, for the rest of the process (and its children); returns the count.  Call it
    once when a command starts, before it computes: BLAS libraries loaded later read the
    environment variables set here, those already loaded are limited through threadpoolctl."""
    global _blas_limit
    n = threads_from_environment() if threads is None else int(threads)
    if n < 1:
        raise ValueError(f"threads = {threads!r}: expected a positive whole number")
    # one core asked for explicitly (an argument, or the variable set to 1) keeps the
    # background task here too; else it is on where a second core exists
    one_core = n == 1 and (threads is not None or os.environ.get(ENVIRONMENT_VARIABLE))
    for variable in BLAS_VARIABLES:
        os.environ[variable] = str(n)
    _small_pages()
    from threadpoolctl import threadpool_limits

    from deltatwin.models import batched
    _blas_limit = threadpool_limits(limits=n, user_api="blas")
    batched.THREADS = n
    batched.BACKGROUND = not one_core and batched.usable_cores() >= 2
    return n


def _small_pages() -> None:
    """numpy's large arrays in small pages (the module docstring), unless the user set
    ``NUMPY_MADVISE_HUGEPAGE``: numpy reads the variable when it loads, so this takes effect in
    the commands (``set_threads`` runs before numpy is imported) and in child processes; a
    program that loaded numpy before calling ``set_threads`` keeps numpy's default (numpy's
    run-time switch is private API)."""
    os.environ.setdefault(HUGEPAGE_VARIABLE, "0")
