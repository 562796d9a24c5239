"""Frozen-trunk feature stores: storage chosen by size, caches read as data, NetVLAD's k-means sample."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from semvpr.core.errors import SemvprError
from semvpr.models.backbones import VGG16Backbone
from semvpr.retrieval.features import FeatureStore, GiB, StoreSettings, choose_storage, place_features
from semvpr.retrieval.initialisation import sample_local_features, static_locations
from tests.helpers import mapped_file

torch.set_num_threads(2)


def test_storage_is_chosen_by_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    from semvpr.retrieval import features

    def disk(free_gib: float, total_gib: float = 500) -> None:
        usage = shutil._ntuple_diskusage(total_gib * GiB, (total_gib - free_gib) * GiB, free_gib * GiB)
        monkeypatch.setattr(features.shutil, "disk_usage", lambda _: usage)

    # Pitts30k at 480x640: ~52k images x 1.2 MB of bf16 pool4 maps = 59.5 GiB; SynthCity ~0.2 GiB.
    pitts = 52_000 * 512 * 30 * 40 * 2
    disk(free_gib=300)  # room: 300 GiB free minus the 2 GiB headroom
    assert choose_storage("auto", 200 * 2**20, tmp_path, ram_gb=8, disk_gb=100) == "ram"
    assert choose_storage("auto", pitts, tmp_path, ram_gb=8, disk_gb=100) == "disk"
    assert choose_storage("auto", pitts, tmp_path, ram_gb=8, disk_gb=50) == "stream"  # over the disk budget
    assert choose_storage("auto", pitts, tmp_path, ram_gb=64, disk_gb=100) == "ram"
    disk(free_gib=61)  # 59 GiB of room: too little for Pitts30k unless it is already cached
    assert choose_storage("auto", pitts, tmp_path, ram_gb=8, disk_gb=1000) == "stream"
    disk(free_gib=62)  # 60 GiB of room: enough
    assert choose_storage("auto", pitts, tmp_path, ram_gb=8, disk_gb=1000) == "disk"
    assert choose_storage("auto", pitts, tmp_path, ram_gb=8, disk_gb=1000, cached=True) == "disk"
    disk(free_gib=1.5, total_gib=10)  # a small disk keeps a tenth of itself free: 0.5 GiB of room
    assert choose_storage("auto", int(0.4 * GiB), tmp_path, ram_gb=0.1, disk_gb=100) == "disk"
    assert choose_storage("auto", int(0.6 * GiB), tmp_path, ram_gb=0.1, disk_gb=100) == "stream"
    assert choose_storage("stream", 1, tmp_path, ram_gb=8, disk_gb=100) == "stream"
    with pytest.raises(SemvprError, match="features.storage='gpu'"):
        choose_storage("gpu", 1, tmp_path, ram_gb=8, disk_gb=100)


@pytest.fixture(scope="module")
def backbone() -> VGG16Backbone:
    torch.manual_seed(0)
    return VGG16Backbone(weights="none", train_from="conv5").eval()


def _places(root: Path, n: int = 6):
    from PIL import Image

    from semvpr.data.places import PlaceSet

    rng = np.random.default_rng(0)
    paths = []
    for side in ("database", "queries"):
        (root / side).mkdir(parents=True, exist_ok=True)
        for i in range(n):
            paths.append(root / side / f"{i}.jpg")
            Image.fromarray(rng.integers(0, 255, (40, 56, 3), dtype=np.uint8)).save(paths[-1])
    utm = np.stack([np.arange(n) * 5.0, np.zeros(n)], 1)
    return PlaceSet("toy", tuple(paths[:n]), tuple(paths[n:]), utm, utm)


@pytest.mark.reproducibility
def test_ram_disk_and_stream_give_the_same_trunk(tmp_path: Path, backbone: VGG16Backbone) -> None:
    places = _places(tmp_path / "img")
    stores = {
        s: place_features(places, backbone, StoreSettings((32, 48), tmp_path / "cache", s, 4, 0))
        for s in ("ram", "disk", "stream")
    }
    assert stores["stream"].db.trunk is None and stores["stream"].db.streams
    ram, disk = stores["ram"].db.trunk, stores["disk"].db.trunk
    assert torch.equal(ram, disk) and ram.dtype == torch.bfloat16 and ram.shape == (6, 512, 2, 3)
    streamed = stores["stream"].db.trunk_of(range(6), backbone)
    assert torch.equal(streamed, ram)
    item = stores["stream"].q.item(2)
    assert set(item) == {"image", "mask"} and item["image"].shape == (3, 32, 48)
    # The disk store's rows are pages of the cache file; the RAM store's are the process's own memory.
    (cache,) = (tmp_path / "cache").glob("trunk-*")
    assert mapped_file(disk.data_ptr()) == cache / "db.npy"
    assert mapped_file(stores["disk"].q.trunk[5].data_ptr()) == cache / "q.npy"
    assert mapped_file(ram.data_ptr()) is None


def test_a_trunk_pass_in_another_precision_is_cached_apart_and_a_batch_size_shares_it(
    tmp_path: Path, backbone: VGG16Backbone
) -> None:
    """fp32 and bf16 trunk outputs are two entries (where the CPU runs bf16 natively; elsewhere bf16 runs fp32:
    one); another batch size gives the same bits, so the same entry."""
    from semvpr.core.precision import bf16_native, job_precision

    places = _places(tmp_path / "img")
    counts = []
    for precision, batch in (("32-true", 4), ("bf16-mixed", 4), ("32-true", 2)):
        with job_precision(precision, "cpu"):
            place_features(places, backbone, StoreSettings((32, 48), tmp_path / "cache", "disk", batch, 0))
        counts.append(len(list((tmp_path / "cache").glob("trunk-*"))))
    assert counts == ([1, 2, 2] if bf16_native("cpu") else [1, 1, 1])


def test_a_foreign_or_damaged_cache_is_refused(tmp_path: Path, backbone: VGG16Backbone) -> None:
    places = _places(tmp_path / "img")
    disk = StoreSettings((32, 48), tmp_path / "cache", "disk", num_workers=0)
    place_features(places, backbone, disk)
    (cache,) = (tmp_path / "cache").glob("trunk-*")
    np.save(cache / "db.npy", np.zeros((6, 3), np.uint16))
    with pytest.raises(SemvprError, match=r"holds uint16\[6, 3\].*delete .*trunk-"):
        place_features(places, backbone, disk)
    np.save(cache / "db.npy", np.array([{"x": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(SemvprError, match="unreadable"):  # never unpickled
        place_features(places, backbone, disk)


def test_kmeans_sample_takes_a_few_locations_of_many_images(backbone: VGG16Backbone) -> None:
    n, c, h, w = 40, 512, 3, 4
    store = FeatureStore(
        tuple(f"i{k}" for k in range(n)),
        (48, 64),
        torch.arange(n, dtype=torch.float32).view(n, 1, 1, 1).expand(n, c, h, w).to(torch.bfloat16),
        None,
    )
    frozen = VGG16Backbone(weights="none", train_from=None).eval()  # identity trainable part
    feats, where = sample_local_features(frozen, store, max_features=50, per_image=5, seed=0)
    # NetVLAD: max_features / per_image images, per_image random locations each.
    assert feats.shape == (50, c) and where.shape == (50, 2)
    images = where[:, 0]
    assert len(images.unique()) == 10 and (images.bincount()[images.unique()] == 5).all()
    assert torch.equal(feats[:, 0], images.float())  # each feature comes from the image it says
    for image in images.unique():
        locations = where[images == image, 1]
        assert len(locations.unique()) == 5 and locations.max() < h * w
    # Fewer locations than asked: all of them; more images than exist: all images.
    feats, where = sample_local_features(frozen, store, max_features=10**6, per_image=100, seed=0)
    assert len(where) == n * h * w and len(where[:, 0].unique()) == n


def test_semantic_init_takes_static_locations_or_the_most_static_of_a_weak_teacher(
    capsys: pytest.CaptureFixture[str],
) -> None:
    fraction = torch.tensor([0.9, 0.1, 0.5, 0.49, 0.0, 1.0, 0.3, 0.2])
    # Enough static locations: exactly those >= 0.5, nothing said.
    assert static_locations(fraction, 3).tolist() == [True, False, True, False, False, True, False, False]
    assert capsys.readouterr().err == ""
    # A teacher calling too few static (here 3 of 8, 5 needed): the 5 most static, and a line saying so.
    assert static_locations(fraction, 5).tolist() == [True, False, True, True, False, True, True, False]
    assert "only 3 of 8" in capsys.readouterr().err
    # None static at all (a teacher that labels everything dynamic) and more needed than sampled: all of them.
    assert static_locations(torch.zeros(4), 10).tolist() == [True] * 4


def test_shape_probes_leave_batchnorm_statistics_alone() -> None:
    from semvpr.models.backbones import ResNet50Backbone
    from semvpr.retrieval.features import grid_size, trunk_shape

    backbone = ResNet50Backbone(train_from="layer3")  # layer3 trainable, in train mode
    before = {k: v.clone() for k, v in backbone.state_dict().items()}
    assert grid_size(backbone, (64, 96)) == (4, 6) and trunk_shape(backbone, (64, 96)) == (512, 8, 12)
    assert backbone.units[4].training
    assert all(torch.equal(before[k], v) for k, v in backbone.state_dict().items())


def test_images_replaced_under_the_same_names_get_new_features(tmp_path: Path, backbone: VGG16Backbone) -> None:
    """The trunk and descriptor caches were keyed by file names only: replaced images gave old features."""
    import hashlib

    from PIL import Image

    places = _places(tmp_path / "img")
    first = place_features(places, backbone, StoreSettings((32, 48), tmp_path / "cache", "disk", num_workers=0))
    before = first.db.trunk.clone()
    path = places.db_paths[0]
    Image.fromarray(np.full((40, 56, 3), 255, np.uint8)).save(path)
    places = dataclasses.replace(places)  # the next run's set: a set hashes its files once
    again = place_features(places, backbone, StoreSettings((32, 48), tmp_path / "cache", "disk", num_workers=0))
    assert len(list((tmp_path / "cache").glob("trunk-*"))) == 2
    assert not torch.equal(again.db.trunk[0], before[0]) and torch.equal(again.db.trunk[1:], before[1:])
    # The key re-derived by hand: sha256 over "<name below the root>\0<size>\0" + the sha256 of the file's
    # first, middle and last 4 KiB (the whole file when it is at most 12 KiB) + "\n", after a version line.
    digest = hashlib.sha256(b"files-identity v3\n")
    for p in places.db_paths:
        data = p.read_bytes()
        n = len(data)
        blocks = data if n <= 3 * 4096 else data[:4096] + data[(n - 4096) // 2 :][:4096] + data[n - 4096 :]
        digest.update(f"{p.relative_to(tmp_path / 'img').as_posix()}\0{n}\0".encode())
        digest.update(hashlib.sha256(blocks).digest() + b"\n")
    assert places.identity("db") == digest.hexdigest()[:16]


def test_a_training_job_holds_its_trunk_maps_in_ram_only_within_the_budget(tmp_path: Path) -> None:
    """Every split's store (train, val, test: what training, mining and validation read) holds its maps in the
    process's memory where they fit ``features.ram_gb``, and reads them from the cache file's pages beyond it."""
    from semvpr.config.build import prepare
    from semvpr.config.plan import job_plan
    from tests.helpers import tiny_config

    for ram_gb, storage in ((8, "ram"), (1e-9, "disk")):
        cfg = tiny_config(tmp_path / "cache", f"features.ram_gb={ram_gb}")
        job = prepare(job_plan(cfg), {})
        assert job.storage == storage and set(job.features) == {"train", "val", "test"}
        for split, features in job.features.items():
            for side, store in (("db", features.db), ("q", features.q)):
                held = mapped_file(store.trunk.data_ptr())
                if storage == "ram":
                    assert held is None, (split, side, held)
                else:
                    assert held is not None and held.name == f"{side}.npy" and held.parent.name.startswith("trunk-")
