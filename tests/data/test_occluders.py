"""CamVid objects pasted into frame-aligned sets (``data.occluders``): the draw, its coverage, its label maps
(what ``mask=oracle`` reads), its cache key and its refusals, on a tiny CamVid and tiny traversals."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.data.benchmarks import read_frames
from semvpr.data.classes import STATIC_NAMES, TRAIN_ID_NAMES
from semvpr.models.masks import OracleMask
from tests.camvid_fixture import write_camvid
from tests.helpers import config

#: A colour the CamVid fixture never draws (its classes are grey, blue, purple and steel blue, ±noise).
MAGENTA = (255, 0, 255)
HW = (96, 128)


def write_plain_frames(root: Path, traversals: tuple[str, ...] = ("day", "night"), n: int = 4) -> Path:
    """Traversals of ``n`` magenta PNG frames each (the same image at every frame of every traversal)."""
    for traversal in traversals:
        (root / traversal).mkdir(parents=True)
        for i in range(n):
            Image.fromarray(np.full((*HW, 3), MAGENTA, np.uint8)).save(root / traversal / f"frame{i:03d}.png")
    return root


@pytest.fixture(scope="module")
def camvid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_camvid(tmp_path_factory.mktemp("camvid"), sizes={"train": 2, "val": 1, "test": 6})


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_plain_frames(tmp_path_factory.mktemp("frames"))


def occluded(frames: Path, cache: Path, camvid: Path, **settings: object):
    spec = {"source": "camvid", "root": str(camvid), "coverage": 0.2, "seed": 0, "min_area": 0.002, **settings}
    return read_frames(frames, "day", "night", 1, occluders=spec, cache_dir=cache)


def pixels(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path))


def test_the_draw_is_deterministic_and_each_image_gets_its_own(frames: Path, camvid: Path, tmp_path: Path) -> None:
    one = occluded(frames, tmp_path / "a", camvid)
    two = occluded(frames, tmp_path / "b", camvid)
    assert one.db_paths[0].parent.parent != two.db_paths[0].parent.parent  # two builds, not one read twice
    for a, b in zip([*one.db_paths, *one.q_paths, *one.db_labels], [*two.db_paths, *two.q_paths, *two.db_labels]):
        assert a.read_bytes() == b.read_bytes()
    # Every frame of both traversals is the same magenta image: only the draw tells them apart.
    maps = [pixels(p) for p in (*one.db_labels, *one.q_labels)]
    assert len({m.tobytes() for m in maps}) == len(maps)
    assert not np.array_equal(pixels(one.db_labels[0]), pixels(one.q_labels[0]))
    assert one.name.endswith("+ CamVid 20% seed 0") and one.db_utm.shape == (4, 2)


@pytest.mark.parametrize("coverage", [0.1, 0.15, 0.2])
def test_the_pasted_pixels_cover_the_asked_fraction(
    frames: Path, camvid: Path, tmp_path: Path, coverage: float
) -> None:
    places = occluded(frames, tmp_path, camvid, coverage=coverage)
    for image, labels in zip([*places.db_paths, *places.q_paths], [*places.db_labels, *places.q_labels]):
        pasted = (pixels(image) != MAGENTA).any(-1)
        assert abs(pasted.mean() - coverage) <= 0.02, image
        # Pasted in the lower part: nothing above the top quarter (the fixture's cars sit at rows h/2..3h/4).
        assert not pasted[: HW[0] // 4].any()
        assert np.isin(pixels(labels)[pasted], [TRAIN_ID_NAMES.index("car")]).all()


def test_the_oracle_mask_is_the_pasted_pixels(frames: Path, camvid: Path, tmp_path: Path) -> None:
    places = occluded(frames, tmp_path, camvid)
    oracle = OracleMask(STATIC_NAMES)
    prob = oracle(None, [], list(places.q_labels))
    static = oracle.static_prob(prob)[:, 0].numpy()
    pasted = np.stack([(pixels(p) != MAGENTA).any(-1) for p in places.q_paths])
    assert pasted.any() and np.array_equal(static == 0, pasted) and set(np.unique(static)) == {0.0, 1.0}


def test_holes_only_keeps_the_images_and_the_draw(frames: Path, camvid: Path, tmp_path: Path) -> None:
    pasted = occluded(frames, tmp_path, camvid)
    holes = occluded(frames, tmp_path, camvid, paste=False)
    for path, original in zip(holes.db_paths, sorted((frames / "day").iterdir())):
        assert path.read_bytes() == original.read_bytes()
    for a, b in zip(holes.q_labels, pasted.q_labels):
        assert a.read_bytes() == b.read_bytes()
    assert holes.name.endswith("(holes only)")


def test_objects_come_from_the_test_split_only(frames: Path, camvid: Path, tmp_path: Path) -> None:
    """Without CamVid's train and val frames the set builds the same, and every pasted object names a test
    frame."""
    only_test = tmp_path / "camvid"
    shutil.copytree(camvid, only_test)
    for split in ("train", "val"):
        shutil.rmtree(only_test / split)
        shutil.rmtree(only_test / f"{split}annot")
        (only_test / f"{split}.txt").unlink()
    full = occluded(frames, tmp_path / "a", camvid)
    test_only = occluded(frames, tmp_path / "b", only_test)
    assert [p.read_bytes() for p in full.q_paths] == [p.read_bytes() for p in test_only.q_paths]
    record = json.loads((full.db_paths[0].parents[2] / "occluders.json").read_text())
    test_names = {line.split()[0].split("/")[-1] for line in (camvid / "test.txt").read_text().splitlines()}
    sources = {p["object"] for image in record["images"].values() for p in image["pasted"]}
    assert sources and sources <= test_names


#: CamVid's SegNet ids of its moving classes (Car, Pedestrian, Bicyclist), as the dataset defines them.
CAMVID_MOVING = (8, 9, 10)


def test_coverage_camvid_draws_each_images_fraction_from_camvid_trains_frames(
    frames: Path, camvid: Path, tmp_path: Path
) -> None:
    """Each image's pasted fraction is one of CamVid train's frames' moving-object shares (a frame without any
    among them: nothing pasted), measured from the train label maps; the test split still gives the objects."""
    from semvpr.data.occluders import camvid_shares

    measured = tmp_path / "camvid"
    shutil.copytree(camvid, measured)
    maps = sorted((measured / "trainannot").iterdir())
    h, w = pixels(maps[0]).shape
    for path, moving in zip(maps, (h * w // 8, 0), strict=True):  # 12.5 % of one frame, none of the other
        ids = np.full(h * w, 3, np.uint8)  # road
        ids[:moving] = np.resize(np.array(CAMVID_MOVING, np.uint8), moving)
        Image.fromarray(ids.reshape(h, w)).save(path)
    assert camvid_shares(measured).tolist() == [0.125, 0.0]
    places = occluded(frames, tmp_path / "cache", measured, coverage="camvid")
    record = json.loads((places.db_paths[0].parents[2] / "occluders.json").read_text())
    assert record["camvid_train_shares"] == {"frames": 2, "mean": 0.0625, "median": 0.0625, "max": 0.125, "p90": 0.1125}
    asked = {name: image["asked"] for name, image in record["images"].items()}
    assert set(asked.values()) == {0.125, 0.0}  # eight images, two values: both drawn
    for image in [*places.db_paths, *places.q_paths]:
        share = asked[image.relative_to(places.root).as_posix()]
        assert abs((pixels(image) != MAGENTA).any(-1).mean() - share) <= 0.01 + 1e-9, image
    assert places.name.endswith("+ CamVid at train coverage seed 0")
    assert places.db_paths[0].parents[2] != occluded(frames, tmp_path / "cache", measured).db_paths[0].parents[2]


def test_every_setting_is_part_of_the_cache_key(frames: Path, camvid: Path, tmp_path: Path) -> None:
    def folder(**settings: object) -> Path:
        return occluded(frames, tmp_path, camvid, **settings).db_paths[0].parents[2]

    base = folder()
    others = [folder(coverage=0.1), folder(seed=1), folder(min_area=0.01), folder(paste=False)]
    assert len({base, *others}) == 5 and folder() == base
    changed = tmp_path / "camvid"
    shutil.copytree(camvid, changed)
    first = sorted((changed / "testannot").iterdir())[0]
    ids = pixels(first).copy()
    ids[0, -1] = 1 - ids[0, -1]  # one label pixel of a test map, same size
    Image.fromarray(ids).save(first)
    assert occluded(frames, tmp_path, changed).db_paths[0].parents[2] != base


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"coverage": 0.0}, "coverage=0.0: expected a fraction"),
        ({"coverage": 0.9}, "coverage=0.9: expected a fraction"),
        ({"source": "cityscapes"}, "source='cityscapes' is not one of ['none', 'camvid']"),
        ({"root": None}, "data.occluders.root is not set"),
        # A folder that is not CamVid: was named seg.root, segment's setting.
        ({"root": "/"}, "CamVid split list /test.txt not found; data.occluders.root must hold test.txt"),
        ({"seed": -1}, "seed=-1"),
        ({"min_area": 1.5}, "min_area=1.5"),
        ({"min_area": 0.9}, "no object of the moving classes"),
        ({"colour": "red"}, "data.occluders.colour is not a setting"),
        ({"coverage": "lots"}, "coverage='lots': expected a fraction of the pixels in (0, 0.5] or camvid"),
        # The fixture's cars stand in a band a quarter of the frame high: 35 % is out of reach.
        ({"coverage": 0.35}, "could not cover 35% of a 128x96 image"),
    ],
)
def test_bad_settings_are_one_line(frames: Path, camvid: Path, tmp_path: Path, settings: dict, message: str) -> None:
    with pytest.raises(SemvprError, match=message.replace("(", r"\(").replace("[", r"\[")) as err:
        occluded(frames, tmp_path, camvid, **settings)
    assert "\n" not in str(err.value)
    assert not list(tmp_path.glob("occluded-*"))


def test_the_frames_config_passes_the_setting_and_the_cache(frames: Path, camvid: Path, tmp_path: Path) -> None:
    from semvpr.config.build import build_places
    from semvpr.config.plan import data_settings

    cfg = config(
        "data=frames",
        f"data.root={frames}",
        "data.database=day",
        "data.queries=night",
        "data.occluders.source=camvid",
        f"data.occluders.root={camvid}",
        "data.occluders.coverage=0.1",
        f"paths.cache_dir={tmp_path}",
        "+ckpt=none",
        config_name="eval",
    )
    test = build_places(data_settings(cfg), ("test",))["test"]
    assert test.q_labels is not None and test.q_paths[0].is_relative_to(tmp_path)
    assert abs(np.mean([(pixels(p) != MAGENTA).any(-1).mean() for p in test.q_paths]) - 0.1) <= 0.02
    assert torch.is_tensor(OracleMask()(None, [], list(test.q_labels)))
