"""The local cluster leaves this process's environment as it found it.

Dask's nanny writes its pre-spawn environment (NUMBA_NUM_THREADS=1, ...) into the parent's
os.environ; numba re-reads NUMBA_NUM_THREADS at every compilation and refuses to compile once
its thread pool started with another count, so a batch in a long-lived process (a test run, a
notebook) broke every later simulation ("Cannot set NUMBA_NUM_THREADS to a different value").
"""

from __future__ import annotations

import os

import pytest

pytest.importorskip("dask.distributed")


def test_local_cluster_restores_the_environment():
    from mecanum_hil.fleet.runner import WORKER_ENV, local_cluster

    before = {key: os.environ.get(key) for key in WORKER_ENV}
    cluster = local_cluster(workers=1, dashboard=False)
    try:
        assert {key: os.environ.get(key) for key in WORKER_ENV} == before
    finally:
        cluster.close()
