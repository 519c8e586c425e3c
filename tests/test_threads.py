"""Tests of cmax._threads: the torch thread-count policy and its scope."""
from __future__ import annotations

import pytest
import torch

from cmax._threads import available_cores, torch_threads, torch_threads_scope


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
