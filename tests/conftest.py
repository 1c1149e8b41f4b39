"""Test-session settings shared by every test module.

Under pytest-xdist (``-n auto``) each worker is its own process: on a 2-core machine two
workers whose OpenBLAS and OpenCV each start a thread per core run four busy threads on
two cores. The matrices of these tests are small, so the extra threads only contend:
measured on the 2-core machine, ``pytest -m "not slow" -n auto`` took 95 s with the
libraries' default threads and 79 s with one thread per worker (same tests, same
results). A serial run (no xdist) keeps the libraries' defaults.
"""

from __future__ import annotations

import os

import pytest

_limits = []  # keeps the thread-pool limit alive for the whole worker session


def pytest_configure(config: pytest.Config) -> None:
    if not hasattr(config, "workerinput"):  # not an xdist worker
        return
    # libraries loaded later (scipy's own OpenBLAS) read the environment when they load;
    # threadpoolctl limits the ones already loaded (numpy's)
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    import numpy  # noqa: F401  (loads numpy's OpenBLAS so that the limit reaches it)
    from threadpoolctl import threadpool_limits

    _limits.append(threadpool_limits(limits=1))
    try:
        import cv2
    except ImportError:  # the tests that need OpenCV say so themselves
        return
    cv2.setNumThreads(1)
