"""The fit's loader: each pass reads the batches it is given, with the same worker processes throughout."""

from __future__ import annotations

import os

import pytest
import torch
from torch.utils.data import Dataset

from semvpr.retrieval import loading
from semvpr.retrieval.loading import FitLoader, loader_settings


class Keys(Dataset):
    """An item is its key and the process that read it."""

    def __getitem__(self, key: tuple[int, str]) -> tuple[tuple[int, str], int]:
        return key, os.getpid()


def _pass(loader: FitLoader, batches: list) -> tuple[list, set[int]]:
    read = [items for items in loader.over(batches)]
    return [[key for key, _ in items] for items in read], {pid for items in read for _, pid in items}


def test_a_fit_loader_reads_each_pass_batches_with_the_workers_it_started_with() -> None:
    """A loader made per sub-epoch forked its workers anew each time; the fit's loader keeps them."""
    loader = FitLoader(Keys(), list, num_workers=2, streams=True, device="cpu")
    first, second = [[(0, "a"), (3, "b")], [(1, "c")]], [[(7, "d")], [], [(2, "e"), (5, "f"), (6, "g")]]
    keys, workers = _pass(loader, first)
    assert keys == first and len(workers) == 2 and os.getpid() not in workers
    keys, again = _pass(loader, second)
    assert keys == second and again <= workers  # the next pass's batches, read by the same processes
    assert _pass(loader, first) == (first, workers)


def test_on_the_cpu_a_cached_store_is_read_in_the_process_itself() -> None:
    loader = FitLoader(Keys(), list, num_workers=2, streams=False, device="cpu")
    assert _pass(loader, [[(0, "a")], [(1, "b")]]) == ([[(0, "a")], [(1, "b")]], {os.getpid()})


def test_a_pass_on_a_gpu_reads_every_store_with_workers_into_pinned_memory() -> None:
    """store_loader (mining refreshes, whitening, eval descriptors) had no workers and no pinned memory on a GPU:
    every batch a synchronous copy from pageable memory, decoded in the process driving the device."""
    from semvpr.retrieval.features import FeatureStore, store_loader

    cached = FeatureStore(("a", "b"), (1, 1), torch.zeros(2, 1, 1, 1), None)
    assert loader_settings(3, streams=False, device="cuda:1") == {"num_workers": 3, "pin_memory": True}
    assert loader_settings(3, streams=False, device="cpu") == {"num_workers": 0, "pin_memory": False}
    assert loader_settings(3, streams=True, device="cpu") == {"num_workers": 3, "pin_memory": False}
    gpu, cpu = store_loader(cached, 2, 3, device="cuda"), store_loader(cached, 2, 3)
    assert (gpu.num_workers, gpu.pin_memory, cpu.num_workers, cpu.pin_memory) == (3, True, 0, False)


@pytest.mark.parametrize(("workers", "ranks", "each"), [(8, 2, 4), (5, 2, 2), (2, 4, 1), (0, 2, 0), (3, 1, 3)])
def test_under_ddp_the_jobs_workers_are_divided_among_its_ranks(
    monkeypatch: pytest.MonkeyPatch, workers: int, ranks: int, each: int
) -> None:
    monkeypatch.setattr(loading, "world", lambda: (ranks - 1, ranks))
    assert loader_settings(workers, streams=True, device="cpu")["num_workers"] == each
    assert loader_settings(workers, streams=False, device="cuda")["num_workers"] == each
