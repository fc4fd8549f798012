"""threads.limit_threads: the BLAS pool (threadpoolctl) and OpenCV's pool at the limit asked for,
ARUCO_RING_THREADS read when no limit is given."""
from __future__ import annotations

import cv2
from threadpoolctl import threadpool_info

from aruco_ring_localization import threads


def _blas_threads():
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_limit_threads_sets_blas_and_opencv(monkeypatch):
    before = cv2.getNumThreads()
    blas_before = _blas_threads()
    try:
        monkeypatch.delenv(threads.ENV_VAR, raising=False)
        assert threads.limit_threads() == 1
        assert _blas_threads(), "no BLAS library found by threadpoolctl: the limit would do nothing"
        assert set(_blas_threads()) == {1}, _blas_threads()
        assert cv2.getNumThreads() == 1
        monkeypatch.setenv(threads.ENV_VAR, "2")
        assert threads.limit_threads() == 2
        assert cv2.getNumThreads() == 2
        monkeypatch.setenv(threads.ENV_VAR, "many")
        assert threads.limit_threads() == 1   # not an integer: warned, one thread
    finally:  # leave the process as it was for the other tests
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=max(blas_before or [1]), user_api="blas")
        cv2.setNumThreads(before)
