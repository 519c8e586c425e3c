"""Tests of cmax._threads: the torch thread-count policy and its scope."""
from __future__ import annotations

import pytest
import torch

from cmax._threads import available_cores, blas_threads_scope, torch_threads, torch_threads_scope


def test_small_work_takes_one_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CMAX_TORCH_THREADS", raising=False)
    assert torch_threads(100, cores=16, load=0.0) == 1
    assert torch_threads(1 << 20, cores=16, load=0.0, small=1 << 21) == 1


@pytest.mark.parametrize("cores, load, expected", [
    (8, 1.0, 8),     # idle but for this process: every core
    (8, 0.0, 8),     # never more than the cores
    (8, 4.0, 5),     # three cores busy elsewhere
    (2, 4.0, 1),     # a busy two-core machine: one thread, never zero
    (2, 1.6, 1),     # rounds: 2 - 1.6 + 1 = 1.4
    (2, 1.4, 2),     # 1.6 rounds up
])
def test_large_work_uses_the_free_cores(monkeypatch, cores, load, expected) -> None:
    monkeypatch.delenv("CMAX_TORCH_THREADS", raising=False)
    assert torch_threads(10**8, cores=cores, load=load) == expected
    assert torch_threads(None, cores=cores, load=load) == expected


def test_environment_overrides_and_is_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CMAX_TORCH_THREADS", "3")
    assert torch_threads(10, cores=1, load=9.0) == 3
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv("CMAX_TORCH_THREADS", bad)
        with pytest.raises(ValueError, match="CMAX_TORCH_THREADS"):
            torch_threads(10)


def test_scope_sets_and_restores(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CMAX_TORCH_THREADS", raising=False)
    before = torch.get_num_threads()
    with torch_threads_scope(10) as n:
        assert n == 1 and torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError):
        with torch_threads_scope(threads=2):
            assert torch.get_num_threads() == 2
            raise RuntimeError("restored on errors too")
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError):
        with torch_threads_scope(threads=0):
            pass


def test_available_cores_is_positive() -> None:
    assert 1 <= available_cores()


def test_blas_scope_sets_every_openblas_and_restores_it() -> None:
    """In a process whose OpenBLAS pools start at 2 threads (numpy's and scipy's), the scope sets each to 1
    and restores 2; ``cmax.fit`` runs its solvers inside such a scope (one BLAS thread with one torch thread)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = """
import warnings
import numpy as np, scipy.optimize
import cmax.fitting.api as api
from cmax._threads import _openblas_pools, blas_threads_scope
from cmax.events import Events
pools = _openblas_pools()
counts = lambda: [int(g()) for _, g in pools]
print("pools", len(pools), "before", counts())
with blas_threads_scope(1):
    print("inside", counts())
print("after", counts())
seen, real = [], api.run_stages
def recording(*a, **k):
    seen.append(counts())
    return real(*a, **k)
api.run_stages = recording
rng = np.random.default_rng(0)
n = 3000
x, t = rng.uniform(10, 50, n), np.sort(rng.integers(0, 50_000, n))
events = Events((x + 40e-6 * t).round().astype(np.int64).clip(0, 63), rng.integers(0, 48, n), t,
                np.ones(n, np.int64), 64, 48)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    api.fit(events, np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), model="flow")
print("during fit", seen[0], "after fit", counts())
"""
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2", "PYTHONPATH": str(root)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines())
    pools = int(lines["pools"].split()[0])
    assert pools >= 1                                   # numpy's OpenBLAS at least
    assert lines["pools"].endswith(str([2] * pools))
    assert lines["inside"] == str([1] * pools) and lines["after"] == str([2] * pools)
    assert lines["during"] == f"fit {[1] * pools} after fit {[2] * pools}"
    with pytest.raises(ValueError, match="threads"):
        with blas_threads_scope(0):
            pass


def test_the_openblas_scan_is_kept_until_a_module_is_imported(monkeypatch):
    """``/proc/self/maps`` is read again only after an import (an OpenBLAS comes with an extension module)."""
    import sys
    import types

    from cmax import _threads

    scans = []
    monkeypatch.setattr(_threads, "_scan_openblas", lambda: scans.append(1) or [("set", "get")])
    monkeypatch.setattr(_threads, "_POOLS_SEEN", None)
    first = _threads._openblas_pools()
    assert _threads._openblas_pools() is first and len(scans) == 1
    monkeypatch.setitem(sys.modules, "cmax_test_new_module", types.ModuleType("cmax_test_new_module"))
    assert _threads._openblas_pools() == first and len(scans) == 2
