"""The training and description steps on each device: every test runs on the CPU, and again on a CUDA GPU where
one is visible (marked ``gpu``; ``python -m pytest -m gpu``), where it must give what the CPU gives."""

from __future__ import annotations

import copy
from collections.abc import Iterator

import numpy as np
import pytest
import torch
from torch.utils.data import Dataset

from semvpr.core.errors import SemvprError
from semvpr.core.precision import fp32
from semvpr.models.aggregators.netvlad import NetVLAD
from semvpr.models.whitening import PCAWhitening
from semvpr.retrieval.features import FeatureStore, HostWrites, kept_on, store_batches, store_loader
from semvpr.retrieval.loading import FitLoader
from semvpr.retrieval.mining import Mining, MiningPool
from semvpr.retrieval.retriever import LossWatch, Retriever
from tests.retrieval.ddp_worker import DIM, Trunk, features

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, CUDA])]


@pytest.fixture(autouse=True)
def _no_tf32() -> Iterator[None]:
    """fp32 on both devices, so that the GPU's results are the CPU's to rounding."""
    with fp32("cpu"):
        yield


@pytest.mark.parametrize("device", DEVICES)
def test_a_store_described_on_the_device_gives_the_cpus_descriptors(device: str) -> None:
    torch.manual_seed(0)
    on_cpu = Retriever(Trunk(), NetVLAD(num_clusters=4, dim=DIM), eval_batch_size=6)
    on_device = copy.deepcopy(on_cpu).to(device)
    train = features()
    rows = [3, 0, 17, 9, 25, 1, 39]
    expected = on_cpu.describe_store(train.db, rows)
    got = on_device.describe_store(train.db, rows)
    assert got.shape == (len(rows), 4 * DIM) and got.dtype == np.float32
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert {p.device.type for p in on_device.parameters()} == {device}


@pytest.mark.parametrize("device", DEVICES)
def test_the_loss_watch_leaves_the_losses_on_the_device_until_it_reads_them(device: str) -> None:
    watch = LossWatch(every=3)
    watch.note(torch.tensor(0.25, device=device), 0, 0)
    watch.note(torch.tensor(float("nan"), device=device), 0, 1)
    assert [loss.device.type for loss in watch.losses] == [device, device]
    with pytest.raises(SemvprError, match="loss became nan at epoch 0 step 1"):
        watch.note(torch.tensor(0.5, device=device), 0, 2)


class Rows(Dataset):
    def __getitem__(self, key: int) -> torch.Tensor:
        return torch.full((2, 3), float(key))


@pytest.mark.parametrize("device", DEVICES)
def test_the_fit_loader_pins_its_batches_for_a_gpu(device: str) -> None:
    loader = FitLoader(Rows(), torch.stack, num_workers=0, streams=False, device=device)
    batches = list(loader.over([[1, 2], [5]]))
    assert [b[:, 0, 0].tolist() for b in batches] == [[1.0, 2.0], [5.0]]
    assert all(b.is_pinned() == (device == "cuda") for b in batches)


@pytest.mark.parametrize("device", DEVICES)
def test_mining_on_the_device_finds_the_cpus_tuples(device: str) -> None:
    train = features()
    mining = Mining(batch_size=3, cache_refresh=7, num_negatives=3, negative_candidates=12, margin=0.5)
    pool = MiningPool.of(train, mining)
    gen = np.random.default_rng(0)
    db_desc = gen.normal(size=(len(train.db), 16)).astype(np.float32)
    q_desc = gen.normal(size=(len(pool.queries), 16)).astype(np.float32)

    def mine(on: str) -> list:
        cache = np.full_like(pool.neg_cache, -1) if pool.neg_cache is not None else None
        rng = np.random.default_rng(1)
        return mining.mine(db_desc, q_desc, train.places, pool.queries, rng, cache, on)

    expected, got = mine("cpu"), mine(device)
    assert len(expected) > 0
    assert [(q, p, n.tolist()) for q, p, n in got] == [(q, p, n.tolist()) for q, p, n in expected]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("rows", [20, 60], ids=["gram", "covariance"])
def test_pca_whitening_is_fitted_on_the_device_it_is_on(device: str, rows: int) -> None:
    gen = torch.Generator().manual_seed(0)
    db = torch.randn(rows, 32, generator=gen) @ torch.randn(32, 32, generator=gen)
    on_cpu = PCAWhitening(32, 6).fit(db)
    on_device = PCAWhitening(32, 6).to(device)
    fit = torch.linalg.eigh
    seen: list[str] = []
    with pytest.MonkeyPatch.context() as patch:  # where the decomposition runs, and in which precision
        patch.setattr(torch.linalg, "eigh", lambda m: seen.append(f"{m.device.type} {m.dtype}") or fit(m))
        on_device.fit(db.numpy())
    assert seen == [f"{device} torch.float64"]
    assert on_device.projection.device.type == device
    # The same axes up to each one's sign.
    cosine = (on_device.projection.cpu() * on_cpu.projection).sum(1) / on_cpu.projection.norm(dim=1) ** 2
    torch.testing.assert_close(cosine.abs(), torch.ones(6), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(on_device.mean.cpu(), on_cpu.mean)


@pytest.mark.parametrize("device", DEVICES)
def test_device_rows_reach_their_host_arrays_once_flushed(device: str) -> None:
    trunk = np.zeros((5, 3), np.uint16)
    masks = np.zeros((5, 2), np.float16)
    writes = HostWrites(torch.device(device))
    values = torch.arange(15, dtype=torch.float32).reshape(5, 3)
    for start in (0, 2, 4):
        rows = slice(start, min(start + 2, 5))
        writes.put(trunk, rows, values[rows].to(device).to(torch.bfloat16).view(torch.uint16))
        writes.put(masks, rows, values[rows, :2].to(device) / 3)
        writes.chunk_done()
    writes.flush()
    np.testing.assert_array_equal(trunk, values.to(torch.bfloat16).view(torch.uint16).numpy())
    np.testing.assert_array_equal(masks, (values[:, :2] / 3).numpy().astype(np.float16))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("with_masks", [True, False], ids=["masks", "no masks"])
def test_store_batches_are_the_loaders_batches_on_the_device(device: str, with_masks: bool) -> None:
    gen = torch.Generator().manual_seed(0)
    trunk = torch.randn(7, 3, 2, 2, generator=gen).to(torch.bfloat16)
    masks = (torch.rand(7, 1, 2, 2, generator=gen) > 0.5).to(torch.float16) if with_masks else None
    store = FeatureStore(tuple(f"{i}.jpg" for i in range(7)), (8, 8), trunk, masks)
    for index in (None, [5, 0, 3, 6, 1]):
        expected = list(store_loader(store, 2, 0, index))
        got = list(store_batches(store, 2, 0, index, device))
        assert len(got) == len(expected)
        for a, b in zip(got, expected, strict=True):
            assert set(a) == set(b) and all(a[k].device.type == device for k in a)
            assert all(a[k].dtype == b[k].dtype and torch.equal(a[k].cpu(), b[k]) for k in a)
    # A GPU keeps the small store from its first pass on; the CPU reads it where it is.
    assert list(store.on_device) == ([torch.device(device)] if device == "cuda" else [])


def test_a_store_too_large_for_a_gpus_free_memory_stays_on_the_host(monkeypatch: pytest.MonkeyPatch) -> None:
    store = FeatureStore(("a.jpg", "b.jpg"), (8, 8), torch.zeros(2, 4, 2, 2, dtype=torch.bfloat16), None)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (4 * store.trunk.nbytes - 1, 10**12))
    assert kept_on(store, torch.device("cuda")) is None and not store.on_device
    assert kept_on(store, torch.device("cpu")) is None


def test_on_a_gpu_a_chunks_rows_are_written_once_the_next_chunk_is_queued(monkeypatch: pytest.MonkeyPatch) -> None:
    """HostWrites' deferred path, on the CPU: the GPU's copy-done events replaced by ones that record their waits."""
    waited: list[int] = []

    class Event:
        def record(self) -> None:
            self.number = len(waited) + 100

        def synchronize(self) -> None:
            waited.append(self.number)

    monkeypatch.setattr(torch.cuda, "Event", Event)
    out = np.zeros(6, np.float32)
    writes = HostWrites(torch.device("cuda"))
    writes.put(out, slice(0, 2), torch.tensor([1.0, 2.0]))
    writes.chunk_done()
    assert not out.any() and not waited  # the first chunk's copy may still run
    writes.put(out, slice(2, 4), torch.tensor([3.0, 4.0]))
    writes.chunk_done()
    np.testing.assert_array_equal(out, [1, 2, 0, 0, 0, 0])  # its event waited for, the second still running
    writes.put(out, slice(4, 6), torch.tensor([5.0, 6.0]))
    writes.flush()
    np.testing.assert_array_equal(out, [1, 2, 3, 4, 5, 6])
    assert len(waited) == 3
    writes.flush()  # nothing left: no wait
    assert len(waited) == 3
