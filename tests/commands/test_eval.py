"""A checkpoint evaluates and localises on every supported dataset family, whatever it was trained on."""

from __future__ import annotations

import csv
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from semvpr.core.errors import SemvprError
from semvpr.eval import evaluate_checkpoint
from semvpr.localize import localize
from tests.bad_input import cli
from tests.helpers import (
    EVAL_SIZE,
    config,
    make_folder,
    mapped_file,
    place_utm,
    record_first_unit_batches,
    tiny_config,
    write_checkpoint,
    write_image,
    write_msls_side,
    write_pitts_mat,
)


def make_pitts(root: Path, mat: str = "pitts30k_test", n: int = 6) -> Path:
    """pytorch-NetVlad layout: db names under root, query names under root/queries_real, same stems."""
    names = [f"000/{i:06d}_pitch1_yaw1.jpg" for i in range(n)]
    for i, name in enumerate(names):
        write_image(root / name, i)
        write_image(root / "queries_real" / name, i)
    write_pitts_mat(root / "datasets" / f"{mat}.mat", "test", names, names)
    return root


def make_msls(root: Path, n: int = 6) -> Path:

    for city, offset in (("cph", 0), ("sf", 100)):
        rows = [(f"{city}{i}", *place_utm(i), False, True) for i in range(n // 2)]
        for side in ("database", "query"):
            write_msls_side(root / "train_val" / city / side, rows)
            for i in range(n // 2):
                write_image(root / "train_val" / city / side / "images" / f"{city}{i}.jpg", offset + i)
    return root


FAMILIES = {
    "folder": (make_folder, ["data=folder"]),
    "pitts30k": (make_pitts, ["data=pitts30k"]),
    "tokyo247": (lambda root: make_pitts(root, "tokyo247"), ["data=tokyo247"]),
    "msls": (make_msls, ["data=msls"]),
}


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_checkpoint_evaluates_on_each_dataset_family(checkpoint: Path, tmp_path: Path, family: str) -> None:
    make, overrides = FAMILIES[family]
    root = make(tmp_path / family)
    cfg = config(
        *overrides,
        f"data.root={root}",
        f"+ckpt={checkpoint}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        *EVAL_SIZE,
        config_name="eval",
    )
    result = evaluate_checkpoint(cfg)
    assert (result["data"], result["aggregator"], result["mask"], result["database"], result["queries"]) == (
        family,
        "sral",
        "none",
        6,
        6,
    )
    # Each query is its place's database image again: any model must retrieve it first.
    assert result["test/R@1"] == 100.0


def test_checkpoint_localises_against_another_dataset(checkpoint: Path, tmp_path: Path) -> None:
    root = make_pitts(tmp_path / "pitts")
    queries = tmp_path / "queries"
    for i in (4, 1):
        write_image(queries / f"q{i}.jpg", i)  # the pixels of database images 4 and 1
    cfg = config(
        "data=pitts30k",
        f"data.root={root}",
        f"+ckpt={checkpoint}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"queries={queries}",
        "top_k=3",
        *EVAL_SIZE,
        config_name="localize",
    )
    results = localize(cfg)
    assert [Path(r["matches"][0]["path"]).name for r in results] == ["000001_pitch1_yaw1.jpg", "000004_pitch1_yaw1.jpg"]
    assert results[0]["matches"][0]["utm"] == list(place_utm(1)) and len(results[0]["matches"]) == 3


def test_localize_on_a_frame_aligned_set_gives_frames_not_utm(checkpoint: Path, tmp_path: Path) -> None:
    """A frame-aligned set's positions are (frame, 0): localize names the frame (it printed them as UTM east and
    north, and wrote them under "utm"); top_k past the database is reported as what was returned."""
    for i in range(3):
        write_image(tmp_path / "nord" / "ref" / f"{i + 10:05d}.jpg", i)
        write_image(tmp_path / "nord" / "query" / f"{i + 10:05d}.jpg", i)
    proc = cli(
        "semvpr.localize",
        f"ckpt={checkpoint}",
        "data=nordland",
        f"data.root={tmp_path / 'nord'}",
        f"queries={tmp_path / 'nord' / 'query'}",
        "top_k=5",
        "threads=1",
        *EVAL_SIZE,
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.run.dir={tmp_path / 'out'}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "out" / "localize.json").read_text())
    matches = [m for r in results for m in r["matches"]]
    assert len(results) == 3 and all(len(r["matches"]) == 3 for r in results)
    assert all("utm" not in m and m["frame"] == int(Path(m["path"]).stem) for m in matches)
    lines = proc.stdout.strip().splitlines()
    assert all(re.search(r": [0-9]{5}\.jpg \(frame 1[0-2], d=[0-9.]+\)$", line) for line in lines[:3]), lines
    assert json.loads(lines[-1])["top_k"] == 3


@pytest.mark.parametrize("filter_name", ["attention", "unet"])
def test_eval_batches_larger_than_the_memory_budget_run_in_chunks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, filter_name: str
) -> None:
    """The eval pipeline (trunk, mask, NetVLAD) takes its batch a few images at a time, so its
    activation memory does not grow with the batch; descriptors are those of one whole-batch pass."""
    import semvpr.models.backbones as backbones
    from semvpr.config.build import build_places
    from semvpr.config.plan import data_settings
    from semvpr.config.restore import load_retriever
    from semvpr.retrieval.descriptors import place_descriptors
    from semvpr.retrieval.features import grid_size

    write_checkpoint(tiny_config(tmp_path, f"filter={filter_name}"), tmp_path / "model.ckpt")
    root = make_folder(tmp_path / "folder", n=5)

    def descriptors(cache: str) -> tuple[np.ndarray, list[int]]:
        cfg = config(
            "data=folder",
            f"data.root={root}",
            f"+ckpt={tmp_path / 'model.ckpt'}",
            f"paths.cache_dir={tmp_path / cache}",
            "model.eval_batch_size=5",
            *EVAL_SIZE,
            config_name="eval",
        )
        retriever, merged = load_retriever(cfg)
        grid_size(retriever.backbone, merged.data.image_size)  # the once-per-size shape probe, before counting
        seen = record_first_unit_batches(retriever.backbone)
        return np.array(
            place_descriptors(
                retriever,
                build_places(data_settings(merged), ("test",))["test"],
                "db",
                merged.data.image_size,
                merged.paths.cache_dir,
            )
        ), seen

    whole, seen = descriptors("whole")
    assert seen == [5, 5]  # the trunk pass over the set: its 5 database images, then its 5 queries
    monkeypatch.setattr(backbones, "FORWARD_BYTES", 1)  # one image per pass
    chunked, seen = descriptors("chunked")
    assert seen == [1] * 10
    # Up to float rounding (another batch size may take another oneDNN kernel; NetVLAD's soft
    # assignment amplifies it): entries are ~1e-2, a misplaced image would differ by that much.
    np.testing.assert_allclose(chunked, whole, rtol=0, atol=1e-4)


def test_a_pickled_descriptor_cache_is_refused_unread(checkpoint: Path, tmp_path: Path) -> None:
    root = make_folder(tmp_path / "folder")
    cfg = config(
        "data=folder",
        f"data.root={root}",
        f"+ckpt={checkpoint}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        *EVAL_SIZE,
        config_name="eval",
    )
    evaluate_checkpoint(cfg)
    for cache in (tmp_path / "cache").glob("descriptors-*"):
        np.save(cache / "descriptors.npy", np.array([{"x": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(SemvprError, match=r"descriptor cache .*descriptors-.* is unreadable \(ValueError\)"):
        evaluate_checkpoint(cfg)


def test_a_descriptor_cache_edited_to_hold_nan_is_named_not_blamed_on_the_checkpoint(
    checkpoint: Path, tmp_path: Path
) -> None:
    root = make_folder(tmp_path / "folder")
    cfg = config(
        "data=folder",
        f"data.root={root}",
        f"+ckpt={checkpoint}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        *EVAL_SIZE,
        config_name="eval",
    )
    evaluate_checkpoint(cfg)
    for cache in (tmp_path / "cache").glob("descriptors-*"):
        desc = np.load(cache / "descriptors.npy", mmap_mode="r+")
        desc[-1, 0] = np.inf
        desc.flush()
    with pytest.raises(SemvprError, match=r"descriptor cache .*descriptors-.* holds values that are not finite"):
        evaluate_checkpoint(cfg)


@pytest.mark.parametrize("ram_gb", [8, 1e-9])
def test_descriptors_read_the_trunk_maps_from_the_cache_pages(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, ram_gb: float
) -> None:
    """Within ``features.ram_gb`` (the storage is ram) or beyond it (disk), a checkpoint's descriptors read every
    image's trunk map from the pages of the cache file and write into the pages of the descriptor cache: the
    process holds no per-image map or descriptor of the set in its own memory, and the descriptors are those of
    the trunk held in RAM, bit for bit."""
    from semvpr.config.build import build_places, feature_storage
    from semvpr.config.plan import data_settings, settings_of
    from semvpr.config.restore import load_retriever
    from semvpr.retrieval.descriptors import place_descriptors
    from semvpr.retrieval.features import StoreSettings, place_features
    from semvpr.retrieval.retriever import Retriever

    write_checkpoint(tiny_config(tmp_path, "filter=none"), tmp_path / "model.ckpt")
    root = make_folder(tmp_path / "folder", n=5)
    cfg = config(
        "data=folder",
        f"data.root={root}",
        f"+ckpt={tmp_path / 'model.ckpt'}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"features.ram_gb={ram_gb}",
        "model.eval_batch_size=2",
        *EVAL_SIZE,
        config_name="eval",
    )
    retriever, merged = load_retriever(cfg)
    test = build_places(data_settings(merged), ("test",))["test"]
    storage = feature_storage(settings_of(merged), retriever.backbone, {"test": test})
    assert storage == ("ram" if ram_gb == 8 else "disk")
    seen: list[tuple[Path | None, Path | None]] = []
    describe_store = Retriever.describe_store

    def spy(self: Retriever, store, index=None, out=None) -> np.ndarray:
        seen.append((mapped_file(store.trunk.data_ptr()), None if out is None else mapped_file(out.ctypes.data)))
        return describe_store(self, store, index, out)

    monkeypatch.setattr(Retriever, "describe_store", spy)
    size, cache = merged.data.image_size, merged.paths.cache_dir
    db = place_descriptors(retriever, test, "db", size, cache, storage)
    q = place_descriptors(retriever, test, "q", size, cache, storage)
    (trunk,) = (tmp_path / "cache").glob("trunk-*")
    assert [t for t, _ in seen] == [trunk / "db.npy", trunk / "q.npy"]
    assert all(d is not None and d.name == "descriptors.npy" and d.is_relative_to(tmp_path / "cache") for _, d in seen)
    monkeypatch.setattr(Retriever, "describe_store", describe_store)
    held = place_features(test, retriever.backbone, StoreSettings(tuple(size), cache, "ram"))
    assert mapped_file(held.db.trunk.data_ptr()) is None  # the RAM store: the process's own memory
    assert np.array_equal(db, retriever.describe_store(held.db)) and np.array_equal(q, retriever.describe_store(held.q))


def _hloc_names(path: Path) -> list[str]:
    """An hloc global-features file's image names as hloc lists them: the parent group of every dataset."""
    import h5py

    names: list[str] = []
    with h5py.File(path, "r") as fh:
        fh.visititems(
            lambda _, obj: names.append(obj.parent.name.strip("/")) if isinstance(obj, h5py.Dataset) else None
        )
    return sorted(set(names))


def test_eval_saves_descriptors_hloc_features_pairs_and_predictions_that_read_back(tmp_path: Path) -> None:
    """save.descriptors / hloc / predictions: the descriptors with their images, hloc's global-feats.h5 read back
    as hloc reads it (names from the datasets' groups, ``global_descriptor``), its pairs the nearest database
    images by those descriptors, and predictions.csv's first rank correct exactly where hits.npz has a hit."""
    import h5py

    root = make_folder(tmp_path / "city", n=5)
    run = tmp_path / "run"
    proc = cli(
        "semvpr.eval",
        "experiment=tiny",
        "ckpt=none",
        "aggregator=gem",
        "data=folder",
        f"data.root={root}",
        *EVAL_SIZE,
        "save.descriptors=true",
        "save.hloc=true",
        "save.predictions=true",
        "save.pairs=3",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.run.dir={run}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((run / "eval.json").read_text())
    exported = ["db_descriptors.npy", "db_images.txt", "q_descriptors.npy", "q_images.txt", "global-feats.h5"]
    assert result["files"] == ["ranks.npy", "hits.npz", *exported, "pairs-retrieval.txt", "predictions.csv"]
    db, q = np.load(run / "db_descriptors.npy"), np.load(run / "q_descriptors.npy")
    db_names, q_names = ((run / f"{s}_images.txt").read_text().splitlines() for s in ("db", "q"))
    assert (
        db.shape == (5, result["descriptor_dim"])
        and q.shape == (5, result["descriptor_dim"])
        and db.dtype == np.float32
    )
    # The folder reader's database and queries are one set's two subfolders: names below its root.
    assert all(n.startswith("test/database/") for n in db_names) and len(set(q_names)) == 5
    assert _hloc_names(run / "global-feats.h5") == sorted(db_names + q_names)
    with h5py.File(run / "global-feats.h5", "r") as fh:
        read = np.stack([fh[n]["global_descriptor"][()] for n in db_names + q_names])
    assert np.array_equal(read, np.concatenate([db, q]))
    distances = ((q[:, None, :].astype(np.float64) - db[None, :, :]) ** 2).sum(-1)
    nearest = np.argsort(distances, axis=1, kind="stable")[:, :3]
    pairs = [line.split(" ") for line in (run / "pairs-retrieval.txt").read_text().splitlines()]
    assert pairs == [[q_names[i], db_names[j]] for i in range(5) for j in nearest[i]]
    with (run / "predictions.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 15 and [r["rank"] for r in rows[:3]] == ["1", "2", "3"]
    hits = np.load(run / "hits.npz")["hits"][:, 0]
    assert [r["correct"] == "true" for r in rows if r["rank"] == "1"] == hits.tolist()
    for row in rows:
        i, j = q_names.index(row["query"]), db_names.index(row["database"])
        assert float(row["distance"]) == pytest.approx(np.sqrt(distances[i, j]), abs=1e-5)


def test_a_bad_save_setting_is_one_line_before_any_pass(tmp_path: Path) -> None:
    proc = cli(
        "semvpr.eval", "experiment=tiny", "ckpt=none", "save.pairs=0", f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path
    )
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        "semvpr: error: save.pairs=0 must be a whole number >= 1 (database images per query)"
    ], proc.stderr[-2000:]


def test_eval_takes_any_two_folders(tmp_path: Path) -> None:
    """data=folders data.database=DIR data.queries=DIR, as VPR-methods-evaluation takes them."""
    root = make_folder(tmp_path / "city", n=4)
    run = tmp_path / "run"
    proc = cli(
        "semvpr.eval",
        "experiment=tiny",
        "ckpt=none",
        "aggregator=gem",
        "data=folders",
        f"data.database={root / 'images' / 'test' / 'database'}",
        f"data.queries={root / 'images' / 'test' / 'queries'}",
        *EVAL_SIZE,
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.run.dir={run}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((run / "eval.json").read_text())
    # Each query is its place's database image again: any model retrieves it first.
    assert (result["set"], result["database"], result["queries"], result["test/R@1"]) == (
        "database→queries",
        4,
        4,
        100.0,
    )


def _pca_sets(tmp_path: Path) -> tuple[Path, Path]:
    """An evaluated folder set (8 places) and a PCA set whose training database holds copies of its images."""
    evaluated = make_folder(tmp_path / "evaluated", n=8)
    fit = tmp_path / "fit" / "images" / "train"
    fit.mkdir(parents=True)
    shutil.copytree(evaluated / "images" / "test" / "database", fit / "database")
    shutil.copytree(evaluated / "images" / "test" / "queries", fit / "queries")
    return evaluated, tmp_path / "fit"


def _pca_eval(tmp_path: Path, evaluated: Path, run: str, *overrides: str) -> dict:
    cfg = config(
        "experiment=tiny",
        "ckpt=none",
        "aggregator=gem",
        "data=folder",
        f"data.root={evaluated}",
        "save.descriptors=true",
        f"paths.cache_dir={tmp_path / 'cache'}",
        *EVAL_SIZE,
        *overrides,
        config_name="eval",
    )
    (tmp_path / run).mkdir()
    return evaluate_checkpoint(cfg, {"aggregator", "data.root", *(o.split("=")[0] for o in overrides)}, tmp_path / run)


def test_pca_at_eval_whitens_with_a_pca_fitted_on_the_named_sets_training_database(tmp_path: Path) -> None:
    """pca.dim / pca.data / pca.root (the benchmark's --pca_dim / --pca_dataset_folder): the descriptors are the
    model's own through a PCA-whitening fitted on the PCA set's training database, as an SVD of those
    descriptors gives it (re-derived here from the unwhitened descriptors, each component up to its sign)."""
    evaluated, fit = _pca_sets(tmp_path)
    plain = _pca_eval(tmp_path, evaluated, "plain")
    pca = _pca_eval(tmp_path, evaluated, "pca", "pca.dim=4", "pca.data=folder", f"pca.root={fit}")
    assert plain["pca"] is None and plain["descriptor_dim"] > 4
    assert pca["pca"] == {"dim": 4, "set": pca["pca"]["set"], "images": 8} and pca["descriptor_dim"] == 4
    # The PCA set's training database holds the evaluated database's images: its descriptors are plain's.
    raw_db, raw_q = (np.load(tmp_path / "plain" / f"{s}_descriptors.npy").astype(np.float64) for s in ("db", "q"))
    mean = raw_db.mean(0)
    _, singular, vt = np.linalg.svd(raw_db - mean, full_matrices=False)
    projection = vt[:4].T / np.sqrt(singular[:4] ** 2 / (len(raw_db) - 1) + 1e-9)
    for side, raw in (("db", raw_db), ("q", raw_q)):
        expected = (raw - mean) @ projection
        expected /= np.linalg.norm(expected, axis=1, keepdims=True)
        got = np.load(tmp_path / "pca" / f"{side}_descriptors.npy")
        signs = np.sign((got * expected).sum(0))  # each principal axis is defined up to its sign
        np.testing.assert_allclose(got, expected * signs, atol=2e-4)


@pytest.mark.parametrize(
    ("overrides", "line"),
    [
        (["pca.dim=0"], r"^pca\.dim=0 must be a whole number from 1"),
        (["pca.dim=4", "pca.data=folders", "pca.overrides=['database=X','queries=Y']"], r"no train split"),
        (["pca.dim=100000", "pca.data=folder", "pca.root=FIT"], r"^pca\.dim=100000: the model's descriptors have"),
        (["pca.dim=4", "pca.data=folder", "pca.root=EVALUATED"], r"^split folder .*/images/train not found"),
    ],
)
def test_pca_at_eval_refuses_what_it_cannot_fit_in_one_line(tmp_path: Path, overrides: list[str], line: str) -> None:
    evaluated, fit = _pca_sets(tmp_path)
    given = [o.replace("FIT", str(fit)).replace("EVALUATED", str(evaluated)) for o in overrides]
    with pytest.raises(SemvprError, match=line):
        _pca_eval(tmp_path, evaluated, "run", *given)


def test_pca_at_eval_never_fits_on_an_evaluated_image(tmp_path: Path) -> None:
    evaluated, fit = _pca_sets(tmp_path)
    cfg_overrides = ["pca.dim=4", "pca.data=folder", f"pca.root={fit}"]
    with pytest.raises(SemvprError, match=r"^pca\.data=folder: 8 of its training images are evaluated here"):
        _pca_eval(tmp_path, fit, "run", *cfg_overrides, "data.test.split=train")


def test_eval_draws_queries_with_their_retrievals_framed_by_the_ground_truth(tmp_path: Path) -> None:
    """save.images=N: N queries' images, each the query then its first save.image_top retrievals, every
    retrieved tile framed green where hits.npz says a positive, red elsewhere; only_wrong draws only queries whose
    first retrieval is wrong. Queries here are other pixels than their place's database image: some miss."""
    from semvpr.reporting.prediction_images import FRAME, GAP, RIGHT, WRONG

    root = make_folder(tmp_path / "city", n=8)
    for i, path in enumerate(sorted((root / "images" / "test" / "queries").iterdir())):
        write_image(path, 100 + i)
    runs = {}
    for name, extra in (("all", []), ("wrong", ["save.only_wrong=true"])):
        (tmp_path / name).mkdir()
        cfg = config(
            *["experiment=tiny", "ckpt=none", "aggregator=gem", "data=folder", f"data.root={root}", *EVAL_SIZE],
            *["save.images=3", "save.image_top=4", f"paths.cache_dir={tmp_path / 'cache'}", *extra],
            config_name="eval",
        )
        runs[name] = evaluate_checkpoint(cfg, {"aggregator", "data.root"}, tmp_path / name)
    top = runs["all"]["top"]
    positives = [np.flatnonzero(np.arange(8) == i) for i in range(8)]  # 100 m apart: a query's own place only
    drawn = [f for f in runs["all"]["exported"] if f.startswith("predictions/")]
    assert drawn == ["predictions/0.jpg", "predictions/4.jpg", "predictions/7.jpg"]  # spread over the queries
    for name in drawn:
        image = np.asarray(Image.open(tmp_path / "all" / name).convert("RGB"), dtype=int)
        tile = (image.shape[1] - 4 * GAP) // 5
        assert image.shape[1] == 5 * tile + 4 * GAP
        i = int(Path(name).stem)
        for rank, j in enumerate(top[i, :4], start=1):
            frame = image[image.shape[0] - FRAME // 2, rank * (tile + GAP) + tile // 2]
            expected = RIGHT if j in positives[i] else WRONG
            assert np.abs(frame - expected).max() < 40, (name, rank, frame)
    wrong = [int(Path(f).stem) for f in runs["wrong"]["exported"] if f.startswith("predictions/")]
    missed = [i for i in range(8) if top[i, 0] != i]
    assert wrong and set(wrong) <= set(missed) and len(wrong) == min(3, len(missed))


def test_drawn_predictions_shade_what_the_mask_weights_down(tmp_path: Path) -> None:
    """With a mask source the drawn images are shaded where its mask weights features down (the oracle's sky and
    dynamic objects here): the same query's tile is darker than without the mask, and its frame unchanged."""
    from semvpr.reporting.prediction_images import CAPTION, FRAME, THUMB_H

    tiles = {}
    for mask in ("none", "oracle"):
        (tmp_path / mask).mkdir()
        cfg = config(
            *["experiment=tiny", "ckpt=none", "aggregator=gem", f"mask={mask}", "save.images=1", "save.image_top=1"],
            f"paths.cache_dir={tmp_path / 'cache'}",
            config_name="eval",
        )
        result = evaluate_checkpoint(cfg, {"aggregator", "mask"}, tmp_path / mask)
        (drawn,) = [f for f in result["exported"] if f.startswith("predictions/")]
        tiles[mask] = np.asarray(Image.open(tmp_path / mask / drawn).convert("L"), dtype=float)
    inside = (slice(CAPTION + FRAME, CAPTION + FRAME + THUMB_H), slice(FRAME, FRAME + 100))
    assert tiles["oracle"][inside].mean() < 0.9 * tiles["none"][inside].mean()
    assert abs(tiles["oracle"][CAPTION + 2, 2] - tiles["none"][CAPTION + 2, 2]) < 10


def test_localize_marks_each_match_right_or_wrong_where_the_query_name_gives_its_position(tmp_path: Path) -> None:
    """Queries named @east@north@... (VPR-datasets-downloader's) are checked: each match's distance in metres and
    whether it is within data.eval_radius; a query named otherwise has neither."""
    root = make_folder(tmp_path / "city", n=6)
    queries = tmp_path / "queries"
    named = sorted((root / "images" / "test" / "queries").iterdir())[2]
    queries.mkdir()
    shutil.copy(named, queries / named.name)  # database image 2's pixels, at its place
    shutil.copy(named, queries / "photo.jpg")  # the same pixels, no position
    cfg = config(
        *["experiment=tiny", "ckpt=none", "aggregator=gem", "data=folder", f"data.root={root}", *EVAL_SIZE],
        *[f"queries={queries}", "top_k=3", f"paths.cache_dir={tmp_path / 'cache'}", "save.images=2"],
        config_name="localize",
    )
    (tmp_path / "run").mkdir()
    results = localize(cfg, {"aggregator", "data.root"}, tmp_path / "run")
    by_name = {Path(r["query"]).name: r for r in results}
    # save.images: each query drawn; its first match framed green where its name says where it was taken, grey
    # where nothing says.
    from semvpr.reporting.prediction_images import FRAME, GAP, RIGHT, UNKNOWN

    for i, result in enumerate(results):
        image = np.asarray(Image.open(tmp_path / "run" / "predictions" / f"{i}.jpg").convert("RGB"), dtype=int)
        tile = (image.shape[1] - 3 * GAP) // 4
        frame = image[image.shape[0] - FRAME // 2, tile + GAP + tile // 2]
        expected = RIGHT if "utm" in result else UNKNOWN
        assert np.abs(frame - expected).max() < 40, (result["query"], frame)
    located = by_name[named.name]
    assert located["utm"] == list(place_utm(2))
    first, *others = located["matches"]
    assert (first["metres"], first["correct"]) == (0.0, True)
    for match in others:  # every other place is 100 m or more away
        assert match["metres"] == pytest.approx(np.hypot(*np.subtract(match["utm"], place_utm(2))))
        assert match["metres"] >= 100 and match["correct"] is False
    assert "utm" not in by_name["photo.jpg"] and all("correct" not in m for m in by_name["photo.jpg"]["matches"])


def test_pca_at_eval_refuses_a_checkpoint_that_has_its_own_whitening(tmp_path: Path) -> None:
    evaluated, fit = _pca_sets(tmp_path)
    write_checkpoint(tiny_config(tmp_path, "filter=none", "aggregator=gem", "model.pca_dim=8"), tmp_path / "w.ckpt")
    cfg = config(
        *["experiment=tiny", f"ckpt={tmp_path / 'w.ckpt'}", "data=folder", f"data.root={evaluated}", *EVAL_SIZE],
        *["pca.dim=4", "pca.data=folder", f"pca.root={fit}", f"paths.cache_dir={tmp_path / 'cache'}"],
        config_name="eval",
    )
    with pytest.raises(SemvprError, match=r"^pca\.dim=4: .*w\.ckpt has its own PCA-whitening \(model\.pca_dim=8\)"):
        evaluate_checkpoint(cfg, {"data.root", "pca.dim", "pca.data", "pca.root"})
