"""Threads set once per process: BLAS libraries loaded before and after, and the chunk pool."""
import os
import subprocess
import sys

import pytest

from deltatwin.threads import ENVIRONMENT_VARIABLE, threads_from_environment


def _run(code: str, threads_env: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items()
           if k not in (ENVIRONMENT_VARIABLE, "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    if threads_env is not None:
        env[ENVIRONMENT_VARIABLE] = threads_env
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=env)


@pytest.mark.parametrize("numpy_first", [False, True])
def test_set_threads_limits_blas_loaded_before_and_after(numpy_first):
    code = ("import numpy\n" if numpy_first else "") + (
        "from deltatwin.threads import set_threads\n"
        "n = set_threads()\n"
        "import scipy.linalg\n"
        "from threadpoolctl import threadpool_info\n"
        "from deltatwin.models import batched\n"
        "blas = [i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas']\n"
        "print(n, batched.THREADS, sorted(set(blas)), len(blas))\n")
    r = _run(code, None)
    assert r.returncode == 0, r.stderr[-2000:]
    n, pool, blas, libraries = r.stdout.split(maxsplit=3)
    assert (n, pool, blas) == ("1", "1", "[1]") and int(libraries) >= 1


def test_threads_from_the_environment(monkeypatch):
    monkeypatch.delenv(ENVIRONMENT_VARIABLE, raising=False)
    assert threads_from_environment() == 1
    monkeypatch.setenv(ENVIRONMENT_VARIABLE, "3")
    assert threads_from_environment() == 3
    monkeypatch.setenv(ENVIRONMENT_VARIABLE, "auto")
    assert threads_from_environment() >= 1
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv(ENVIRONMENT_VARIABLE, bad)
        with pytest.raises(ValueError, match=f"{ENVIRONMENT_VARIABLE}='{bad}'"):
            threads_from_environment()


@pytest.mark.parametrize("env, expected", [(None, "True"), ("1", "False"), ("2", "True")])
def test_the_background_process_is_on_unless_one_core_is_asked_for(env, expected):
    code = ("import os\n"
            "os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:2])\n"
            "from deltatwin.threads import set_threads\n"
            "from deltatwin.models import batched\n"
            "set_threads()\n"
            "print(batched.BACKGROUND if batched.usable_cores() >= 2 else 'one core')\n")
    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity on this system")
    r = _run(code, env)
    assert r.returncode == 0, r.stderr[-2000:]
    if r.stdout.strip() == "one core":
        pytest.skip("this machine has one core")
    assert r.stdout.strip() == expected


def _failing(message):
    raise ValueError(message)


@pytest.mark.parametrize("background", [False, True])
def test_in_background_returns_the_result_or_raises_the_error(monkeypatch, background):
    import numpy as np

    from deltatwin.models import batched
    monkeypatch.setattr(batched, "BACKGROUND", background)
    parent = os.getpid()
    x = np.arange(10.0)
    done = batched.in_background(lambda a, b=0.0: (os.getpid(), a @ a + b), x, b=1.0)
    pid, value = done()
    assert value == 286.0
    assert (pid != parent) == (background and sys.platform.startswith("linux"))
    failed = batched.in_background(_failing, "bad input at row 3")
    with pytest.raises(ValueError, match="bad input at row 3"):
        failed()


def test_a_background_result_never_asked_for_leaves_no_process(monkeypatch, tmp_path):
    import gc
    import time

    from deltatwin.models import batched
    if not sys.platform.startswith("linux"):
        pytest.skip("the background process is forked on Linux only")
    monkeypatch.setattr(batched, "BACKGROUND", True)
    mark = tmp_path / "pid"

    def task():
        mark.write_text(str(os.getpid()))
        time.sleep(30)
    done = batched.in_background(task)
    for _ in range(200):                       # until the child has started
        if mark.exists() and mark.read_text():
            break
        time.sleep(0.05)
    pid = int(mark.read_text())
    del done
    gc.collect()
    with pytest.raises(ChildProcessError):      # stopped and waited for: not our child any more
        os.waitpid(pid, os.WNOHANG)
    with pytest.raises(ProcessLookupError):     # and gone
        os.kill(pid, 0)


class _UnpicklableError(Exception):
    """An error that cannot cross a pipe as itself (pickling it fails; an exception whose
    constructor takes other arguments than its message may fail on unpickling the same way,
    unless a library such as tblib has patched exception pickling)."""

    def __reduce__(self):
        raise TypeError("cannot pickle this error")


def _failing_oddly():
    raise _UnpicklableError("ifm: no light")


def _blas_threads():
    from threadpoolctl import threadpool_info
    return max((p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"),
               default=1)


def test_a_background_result_is_taken_once_and_its_errors_keep_their_traceback(monkeypatch):
    """The forked child's error arrives with the child's traceback as a note (its own type where
    it unpickles, else a RuntimeError naming it); a result taken twice is refused by name (the
    second read would use a closed, maybe reused, file descriptor); the child's BLAS has one
    thread (the caller's pool is not doubled)."""
    from threadpoolctl import threadpool_limits

    from deltatwin.models import batched
    if not sys.platform.startswith("linux"):
        pytest.skip("the background process is forked on Linux only")
    monkeypatch.setattr(batched, "BACKGROUND", True)
    failed = batched.in_background(_failing, "bad input at row 3")
    with pytest.raises(ValueError, match="bad input at row 3") as info:
        failed()
    assert any("in _failing" in n and "background process" in n
               for n in getattr(info.value, "__notes__", [])), info.value
    with pytest.raises(RuntimeError, match="_UnpicklableError: ifm: no light.*_failing_oddly"):
        batched.in_background(_failing_oddly)()
    with threadpool_limits(limits=2, user_api="blas"):
        done = batched.in_background(_blas_threads)
        assert done() == 1
    with pytest.raises(RuntimeError, match="already taken"):
        done()


@pytest.mark.parametrize("numpy_first, user, expected", [
    (False, None, "False 0"), (True, None, "True 0"), (False, "1", "True 1"),
    (True, "1", "True 1")])
def test_set_threads_takes_numpys_arrays_in_small_pages_unless_the_user_chose(
        numpy_first, user, expected):
    """The commands call set_threads before numpy loads: numpy then takes small pages; a
    user's own setting, or numpy loaded first, keeps numpy's choice (read through numpy's
    private switch, which returns the previous state)."""
    code = ("import numpy\n" if numpy_first else "") + (
        "import os\n"
        "from deltatwin.threads import set_threads\n"
        "set_threads()\n"
        "from numpy._core.multiarray import _set_madvise_hugepage\n"
        "print(_set_madvise_hugepage(False), os.environ['NUMPY_MADVISE_HUGEPAGE'])\n")
    env_code = (f"import os; os.environ['NUMPY_MADVISE_HUGEPAGE'] = {user!r}\n" if user
                else "import os; os.environ.pop('NUMPY_MADVISE_HUGEPAGE', None)\n")
    r = _run(env_code + code, None)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == expected
