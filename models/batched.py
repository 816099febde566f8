"""Small vector and matrix algebra on batches stored structure-of-arrays: a vector is (3, ...)
with its component first, a matrix (n, n, ...) with its entries first, and the batch (one
entry per pose) runs along the trailing axes.  Each numpy call then works on thousands of
poses at once, where ``np.sum(a * b, axis=-1)`` over a length-3 axis, ``np.cross`` or a batched
``np.linalg.solve`` of 6x6 systems pay per-item overhead many times the arithmetic.
"""
from __future__ import annotations

import os
import pickle
import signal
import sys
import traceback
import weakref
from concurrent.futures import ThreadPoolExecutor

import numpy as np

# below this rotation angle (rad) the Rodrigues coefficients come from their Taylor series
# (truncation error < angle^6 / 5040 ~ 2e-22: exact in float64)
_SERIES_ANGLE = 1e-3


# points per chunk of a batched computation: a chunk's working set stays in the CPU caches
CHUNK_POINTS = 2048


def usable_cores() -> int:
    """Processors this process may run on (its affinity where the system reports one: Linux;
    else the machine's count: macOS, Windows)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


# threads that ``map_chunks`` solves chunks on (numpy releases the GIL inside its loops); one
# by default, so that processes side by side do not oversubscribe the cores: an application
# raises it once at start-up (deltatwin/threads.py, docs/performance.md)
THREADS = 1
# whether ``in_background`` may start a second process; off by default (a library user's
# process computes where it is), on in a command where a second core exists (deltatwin/threads.py)
BACKGROUND = False


def map_chunks(fun, n_points: int, chunk: int | None = None) -> list:
    """``fun(slice)`` over chunks of ``chunk`` (default CHUNK_POINTS) points, on THREADS
    threads; results in order.  Each chunk writes its own rows, so results do not depend on
    the thread count."""
    chunk = chunk or CHUNK_POINTS
    chunks = [slice(s, s + chunk) for s in range(0, n_points, chunk)]
    if THREADS < 2 or len(chunks) < 2:
        return [fun(sl) for sl in chunks]
    with ThreadPoolExecutor(min(THREADS, len(chunks))) as pool:
        return list(pool.map(fun, chunks))


def _on_one_blas_thread(fun, *args, **kwargs):
    """``fun(*args, **kwargs)`` with BLAS on one thread: a threaded BLAS sums in another order,
    so the result would otherwise depend on where it ran (forked child or caller)."""
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=1, user_api="blas"):
        return fun(*args, **kwargs)


def _computed_now(fun, *args, **kwargs):
    """``fun(*args, **kwargs)`` computed at once, as a forked child would compute it (on the
    arguments as they are now, BLAS on one thread) and as it would send it: through pickle,
    which makes arrays C-ordered (a strided array multiplies in another order, to the last
    bit); returns the function that gives its result or raises its exception, once."""
    try:
        value = pickle.loads(pickle.dumps(_on_one_blas_thread(fun, *args, **kwargs),
                                          pickle.HIGHEST_PROTOCOL))
        raised = None
    except Exception as exc:
        value, raised = None, exc
    taken = []

    def result():
        if taken:
            raise RuntimeError(f"the result of {fun.__name__} was already taken")
        taken.append(True)
        if raised is not None:
            raise raised
        return value
    return result


def in_background(fun, *args, **kwargs):
    """Start ``fun(*args, **kwargs)``; returns a function that waits for its result (or raises
    its exception).  With BACKGROUND on Linux (where a fork is safe) it runs in a forked
    child process, beside what the caller computes meanwhile: a second core for a whole
    independent task of a second or so (a thread would hold the GIL for its Python between the
    numpy calls; the child shares the caller's arrays copy-on-write and sends back only its
    result, pickled; its BLAS on one thread, here as there, the caller's own pool not
    doubled). Else it runs at once, on the arguments as they are (as the child would). The
    result is the same provided the caller does not change the arguments meanwhile (the child
    computes on them as they were at the start)."""
    if not BACKGROUND or not sys.platform.startswith("linux"):
        return _computed_now(fun, *args, **kwargs)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:                                 # the child: compute, send, leave at once
        try:
            os.close(read)
            try:
                done = pickle.dumps((True, _on_one_blas_thread(fun, *args, **kwargs)),
                                    pickle.HIGHEST_PROTOCOL)
            except BaseException as exc:
                # the exception itself where it pickles (the caller handles its type as it
                # would here), and its text and the child's traceback (it arrives without one)
                try:
                    raised = pickle.dumps(exc, pickle.HIGHEST_PROTOCOL)
                except Exception:
                    raised = None
                done = pickle.dumps((False, raised, f"{type(exc).__name__}: {exc}",
                                     traceback.format_exc()), pickle.HIGHEST_PROTOCOL)
            with os.fdopen(write, "wb") as out:
                out.write(done)
        finally:
            os._exit(0)      # no exit handlers, no flush of the parent's buffered output
    os.close(write)

    def result():
        if not abandoned.alive:        # detached when the result was taken
            raise RuntimeError(f"the background result of {fun.__name__} was already taken")
        try:
            with os.fdopen(read, "rb") as channel:
                data = channel.read()
            os.waitpid(pid, 0)
        except BaseException:
            _stop(pid, None)           # interrupted while waiting: the child is not left behind
            raise
        finally:
            abandoned.detach()
        if not data:
            raise RuntimeError(f"the background process computing {fun.__name__} ended "
                               "without a result")
        return _outcome(pickle.loads(data), fun.__name__)
    # a result never asked for (the caller failed first): the child is stopped and waited for
    abandoned = weakref.finalize(result, _stop, pid, read)
    return result


def _stop(pid: int, channel: int | None) -> None:
    if channel is not None:
        os.close(channel)
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass


def _outcome(done: tuple, name: str):
    if done[0]:
        return done[1]
    _, raised, what, where = done
    note = f"raised in the background process computing {name}; its traceback:\n{where}"
    try:
        # an exception whose constructor takes other arguments than its message pickles but
        # does not unpickle
        exc = pickle.loads(raised) if raised is not None else None
    except Exception:
        exc = None
    if exc is None:
        raise RuntimeError(f"{what} ({note})")
    exc.add_note(note)
    raise exc


def dot(a, b):
    """Scalar products of component-first vectors a, b (3, ...) -> (...)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a, b, out=None):
    """Cross products of component-first vectors (3, ...), broadcasting; into ``out`` if given."""
    if out is None:
        out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        np.multiply(a[j], b[k], out=out[i, ...])      # [i, ...]: an array even for (3,) vectors
        out[i, ...] -= a[k] * b[j]
    return out


def matvec(M, v, out=None):
    """Products M v of matrices (3, 3, ...) and vectors (3, ...), broadcasting -> (3, ...)."""
    if out is None:
        out = np.empty((3,) + np.broadcast_shapes(M.shape[2:], v.shape[1:]))
    for i in range(3):
        np.multiply(M[i, 0], v[0], out=out[i, ...])
        out[i, ...] += M[i, 1] * v[1]
        out[i, ...] += M[i, 2] * v[2]
    return out


def matmul(A, B):
    """Products A B of matrices (3, 3, ...) -> (3, 3, ...)."""
    out = np.empty((3, 3) + np.broadcast_shapes(A.shape[2:], B.shape[2:]))
    for j in range(3):
        matvec(A, B[:, j], out=out[:, j])
    return out


def rotation_matrices(rotvec):
    """Rotation matrices (3, 3, ...) of rotation vectors (3, ...) (rad): Rodrigues,
    R = I + a [w]x + b [w]x^2 with a = sin(t)/t, b = (1 - cos t)/t^2 = 2 sin^2(t/2)/t^2."""
    t2 = dot(rotvec, rotvec)
    a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
    b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    large = t2 >= _SERIES_ANGLE ** 2
    if large.any():          # rare: Newton's rotation steps are micro-radians
        t = np.sqrt(t2[large])
        a[large] = np.sin(t) / t
        b[large] = 2.0 * (np.sin(0.5 * t) / t) ** 2
    x, y, z = rotvec
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    R = np.empty((3, 3) + t2.shape)
    R[0, 0], R[0, 1], R[0, 2] = 1.0 - bz * z - by * y, bx * y - az, bx * z + ay
    R[1, 0], R[1, 1], R[1, 2] = bx * y + az, 1.0 - bz * z - bx * x, by * z - ax
    R[2, 0], R[2, 1], R[2, 2] = bx * z - ay, by * z + ax, 1.0 - by * y - bx * x
    return R


def left_jacobian(rotvec):
    """(3, 3, ...) the exponential map's left Jacobian at rotation vectors (3, ...):
    exp([w + dw]x) = exp([J dw]x) exp([w]x) to first order in dw,
    J = I + b [w]x + c [w]x^2 with b = (1 - cos t)/t^2, c = (t - sin t)/t^3."""
    t2 = dot(rotvec, rotvec)
    b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    c = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    large = t2 >= _SERIES_ANGLE ** 2
    if large.any():
        t = np.sqrt(t2[large])
        b[large] = (1.0 - np.cos(t)) / t ** 2
        c[large] = (t - np.sin(t)) / t ** 3
    x, y, z = rotvec
    J = np.empty((3, 3) + t2.shape)
    # [w]x^2 = w w^T - t^2 I
    J[0, 0], J[1, 1], J[2, 2] = (1.0 + c * (x * x - t2), 1.0 + c * (y * y - t2),
                                 1.0 + c * (z * z - t2))
    J[0, 1], J[1, 0] = c * x * y - b * z, c * x * y + b * z
    J[0, 2], J[2, 0] = c * x * z + b * y, c * x * z - b * y
    J[1, 2], J[2, 1] = c * y * z - b * x, c * y * z + b * x
    return J


def cholesky(K):
    """Cholesky factors of symmetric positive-definite matrices K (n,n,...), outer-product form:
    the lower triangle holds the factor L, with the reciprocal of L's diagonal on the diagonal
    (for the substitutions); NaN where K is not positive definite."""
    L = K.copy()
    n = K.shape[0]
    for j in range(n):
        pivot = L[j, j]
        inv_diag = 1.0 / np.sqrt(np.where(pivot > 0.0, pivot, np.nan))
        if j + 1 < n:
            col = L[j + 1:, j]
            col *= inv_diag
            L[j + 1:, j + 1:] -= col[:, None] * col[None]
        L[j, j] = inv_diag
    return L


def forward_substitute(L, b):
    """Solve L x = b for factors from ``cholesky``; b (n, ...) broadcasting against L[i, k]."""
    x = b.copy()
    for i in range(L.shape[0]):
        for k in range(i):
            x[i] -= L[i, k] * x[k]
        x[i] *= L[i, i]
    return x


def backward_substitute(L, b):
    """Solve L^T x = b for factors from ``cholesky``."""
    n = L.shape[0]
    x = b.copy()
    for i in reversed(range(n)):
        for k in range(i + 1, n):
            x[i] -= L[k, i] * x[k]
        x[i] *= L[i, i]
    return x


def normal_factor(G):
    """Cholesky factors (``cholesky``) of the normal matrices G G^T (n,n,...) of rows
    G (n, r, ...): r equations of n unknowns each, r >= n, full rank (else NaN)."""
    return cholesky(np.einsum("ir...,jr...->ij...", G, G))


def least_squares_step(L, G, f):
    """x minimising |G^T x + f| (f (r, ...)) by the normal equations G G^T x = -G f, with
    L = ``normal_factor(G)``."""
    return backward_substitute(L, forward_substitute(L, -np.sum(G * f, axis=1)))
