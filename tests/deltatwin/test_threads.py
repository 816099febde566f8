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
