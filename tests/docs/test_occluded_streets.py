"""experiments/occluded-streets end to end on fixtures: run.sh's evaluations (a tiny CamVid, three tiny
traversals, the tiny SynthCity for NetVLAD's k-means; a student and a teacher directory and a checkpoint)
and summarize.py's data file, checked against the ranks the evaluations wrote; mask_iou.py's scores."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.camvid_fixture import write_camvid
from tests.helpers import REPO, write_frames

EXPERIMENT = REPO / "experiments" / "occluded-streets"
#: run.sh's settings for fixtures: tiny images, one job at a time, the tiny SynthCity for NetVLAD's k-means.
TINY = (
    "data.num_workers=0 data.image_size=[64,96] hydra.launcher.n_jobs=1 experiment=tiny "
    "init.overrides=['preset=tiny','image_size=[64,80]']"
)


def _places(tmp_path: Path) -> tuple[Path, Path]:
    """Three tiny traversals whose frame i is the same image (clean, every query finds its place) and a tiny
    CamVid."""
    gardens = write_frames(
        tmp_path / "gardens", {t: [0, 1, 2, 3, 4] for t in ("day_left", "day_right", "night_right")}, "Image{:03d}.jpg"
    )
    return gardens, write_camvid(tmp_path / "camvid", sizes={"train": 1, "val": 1, "test": 6})


def _run_and_summarize(tmp_path: Path, gardens: Path, camvid: Path, env: dict[str, str]) -> dict[tuple, dict]:
    """run.sh into ``tmp_path/out`` and summarize.py into ``tmp_path/summary``; the summary's rows by
    (model, condition, mask, coverage)."""
    for command, limit in (
        (["bash", str(EXPERIMENT / "run.sh"), str(tmp_path / "out"), str(gardens), str(camvid)], 1500),
        (
            [
                sys.executable,
                str(EXPERIMENT / "summarize.py"),
                str(tmp_path / "out"),
                "--out-dir",
                str(tmp_path / "summary"),
            ],
            300,
        ),
    ):
        proc = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=limit)
        assert proc.returncode == 0, proc.stderr[-3000:]
    return {
        (r["model"], r["condition"], r["mask"], int(r["coverage"])): r
        for r in csv.DictReader((tmp_path / "summary" / "results.csv").open())
    }


@pytest.mark.slow
def test_run_sh_and_summarize_on_fixtures(tmp_path: Path) -> None:
    gardens, camvid = _places(tmp_path)
    out = tmp_path / "out"
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "PAIRS": "day_left:night_right",
        "COVERAGES": "0.1,0.2",
        "SEEDS": "0,1",
        "EXTRA": TINY,
    }
    rows = {k[1:]: r for k, r in _run_and_summarize(tmp_path, gardens, camvid, env).items()}
    sweeps = sorted(p.name for p in (out / "eval" / "day_left-night_right").iterdir())
    assert sweeps == ["m0-clean-none", "m0-holes-oracle", "m0-occluded-none", "m0-occluded-oracle"]
    assert set(rows) == {("clean", "none", 0)} | {
        (c, m, cov) for c, m in (("occluded", "none"), ("occluded", "oracle"), ("holes", "oracle")) for cov in (10, 20)
    }
    assert float(rows["clean", "none", 0]["r1"]) == 100.0
    # Every R@1 re-read from the jobs' ranks, by the set name each job's eval.json carries.
    for job in (out / "eval" / "day_left-night_right").glob("m0-*/*/ranks.npy"):
        condition, mask = job.parent.parent.name.split("-")[1:]
        name = (job.parent / "eval.json").read_text()
        coverage = 0 if condition == "clean" else (10 if "CamVid 10%" in name else 20)
        row = rows[condition, mask, coverage]
        ranks = [np.load(p) for p in job.parent.parent.glob("*/ranks.npy") if _coverage(p) == coverage]
        assert float(row["r1"]) == pytest.approx(100 * np.mean([np.mean(r == 0) for r in ranks]), abs=0.01)
        assert (int(row["models"]), int(row["runs"])) == (1, 1 if condition == "clean" else 2)
    for coverage in (10, 20):
        none, oracle = rows["occluded", "none", coverage], rows["occluded", "oracle", coverage]
        # Paired by query over the seeds' mean hit rate: the gain is the difference of the mean R@1s.
        assert float(oracle["gain"]) == pytest.approx(float(oracle["r1"]) - float(none["r1"]), abs=0.02)
        holes = rows["holes", "oracle", coverage]
        assert float(holes["gain"]) == pytest.approx(float(holes["r1"]) - 100.0, abs=0.02)
        assert float(oracle["leak"]) == pytest.approx(float(oracle["r1"]) - float(holes["r1"]), abs=0.02)
        if oracle["recovered"]:
            expected = (float(oracle["r1"]) - float(none["r1"])) / (100.0 - float(none["r1"]))
            assert float(oracle["recovered"]) == pytest.approx(expected, abs=0.002)
    assert (tmp_path / "summary" / "figure_coverage.png").stat().st_size > 0
    assert (
        "| NetVLAD (k-means, no VPR training) | occluded | 20 % | oracle"
        in (tmp_path / "summary" / "results.md").read_text()
    )


def _coverage(ranks: Path) -> int:
    text = (ranks.parent / "eval.json").read_text()
    return 10 if "CamVid 10%" in text else 20 if "CamVid 20%" in text else 0


@pytest.mark.slow
def test_run_sh_with_segmenters_and_checkpoints_on_fixtures(tmp_path: Path) -> None:
    """run.sh's CAMVID_STUDENT / CAMVID_TEACHER / CKPTS path: a student and a teacher directory as semvpr.segment
    saves them and a tiny training run's checkpoint, every mask on every model; summarize.py's rows for
    them; mask_iou.py's IoU against the pasted pixels, the student's re-derived here from its own forward pass."""
    from semvpr.config.build import build_backbone
    from semvpr.data.classes import TRAIN_ID_NAMES
    from semvpr.models.student import load_student
    from tests.helpers import frame_images, tiny_config, write_student_dir, write_teacher_dir

    gardens, camvid = _places(tmp_path)
    backbone = build_backbone(tiny_config(tmp_path / "fixture-cache").backbone, 0).eval()
    student = write_student_dir(tmp_path / "seg" / "student", backbone, frame_images(gardens, "day_left"))
    teacher = write_teacher_dir(tmp_path / "seg" / "teacher")
    out, cache = tmp_path / "out", tmp_path / "cache"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    # A trained checkpoint: a tiny training run (seconds; its SynthCity is the one run.sh's k-means reads).
    train = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.train",
            "experiment=tiny",
            "filter=none",
            f"paths.cache_dir={cache}",
            "threads=1",
            f"hydra.run.dir={tmp_path / 'runs' / 'tiny-none'}",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert train.returncode == 0, train.stderr[-3000:]
    ckpt = tmp_path / "runs" / "tiny-none" / "checkpoints" / "best.ckpt"
    env |= {
        "CACHE": str(cache),
        "PAIRS": "day_left:night_right",
        "COVERAGES": "0.2",
        "SEEDS": "0,1",
        "CAMVID_STUDENT": str(student),
        "CAMVID_TEACHER": str(teacher),
        "CKPTS": f"'{ckpt}'",
        "EXTRA": TINY,
    }
    rows = _run_and_summarize(tmp_path, gardens, camvid, env)
    cells = [
        f"{c}-{m}" for c, m in [("clean", "none"), ("occluded", "none"), ("occluded", "oracle"), ("holes", "oracle")]
    ]
    cells += [f"{c}-{m}" for c in ("clean", "occluded") for m in ("student", "teacher")]
    sweeps = sorted(p.name for p in (out / "eval" / "day_left-night_right").iterdir())
    assert sweeps == sorted(f"m{i}-{cell}" for i in (0, 1) for cell in cells)
    for found in (out / "eval" / "day_left-night_right").glob("*/*/eval.json"):
        result = json.loads(found.read_text())
        assert result["status"] == "ok", (found, result.get("error"))
        segmenter = {"student": str(student), "teacher": str(teacher)}.get(result["mask"])
        assert result["mask_checkpoint"] == segmenter, found
    models = {"untrained netvlad", "tiny-none"}
    assert {k[0] for k in rows} == models
    for model in models:
        clean = float(rows[model, "clean", "none", 0]["r1"])
        occluded = float(rows[model, "occluded", "none", 20]["r1"])
        for mask in ("student", "teacher"):
            for key in ((model, "clean", mask, 0), (model, "occluded", mask, 20)):
                row = rows[key]
                assert all(0 <= float(row[k]) <= 100 for k in ("r1", "r5")), row
                base = clean if key[1] == "clean" else occluded
                assert float(row["gain"]) == pytest.approx(float(row["r1"]) - base, abs=0.02)
            row = rows[model, "occluded", mask, 20]
            if row["recovered"]:  # given only where the damage's interval excludes 0
                assert clean != occluded
                expected = (float(row["r1"]) - occluded) / (clean - occluded)
                assert float(row["recovered"]) == pytest.approx(expected, abs=0.002)
            assert row["leak"] == ""  # the leak is the oracle's only
    text = (tmp_path / "summary" / "results.md").read_text()
    assert "| tiny-none | occluded | 20 % | CamVid teacher" in text
    assert "| NetVLAD (k-means, no VPR training) | clean | 0 % | CamVid student" in text

    iou = subprocess.run(
        [
            sys.executable,
            str(EXPERIMENT / "mask_iou.py"),
            str(out),
            "--source",
            f"student={student}",
            "--source",
            f"teacher={teacher}",
            "--camvid",
            str(camvid),
            "--cache",
            str(cache),
            "--out-dir",
            str(tmp_path / "summary"),
            "--image-size",
            "64",
            "96",
            "seg.image_size=[32,48]",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert iou.returncode == 0, iou.stderr[-3000:]
    scores = {(r["source"], r["images"]): r for r in csv.DictReader((tmp_path / "summary" / "mask_iou.csv").open())}
    assert set(scores) == {(s, i) for s in ("student", "teacher") for i in ("camvid test", "composites")}
    for row in scores.values():
        assert all(0 <= float(row[k]) <= 1 for k in ("object_iou", "objects_removed", "rest_removed")), row
    composite = scores["student", "composites"]
    assert (int(composite["coverage"]), int(composite["seeds"]), int(composite["frames"])) == (20, 2, 20)
    # The student's composites re-scored here: its static probability from the trunk's frozen outputs at each
    # image's size, removed below 0.5, against the label maps' pasted (non-building) pixels.
    model = load_student(student, backbone)
    hit = union = 0
    for key_file in cache.glob("occluded-*/key.json"):
        if not json.loads(key_file.read_text())["paste"]:
            continue
        for name in json.loads((key_file.parent / "occluders.json").read_text())["images"]:
            image = np.asarray(Image.open(key_file.parent / "images" / name).convert("RGB"))
            pasted = np.asarray(Image.open((key_file.parent / "labels" / name).with_suffix(".png"))) != (
                TRAIN_ID_NAMES.index("building")
            )
            batch = torch.from_numpy(image.copy()).permute(2, 0, 1)[None].float() / 255
            with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
                skips = backbone.forward_frozen(batch)
            with torch.no_grad():
                removed = model.static_prob(skips, out_hw=pasted.shape)[0, 0].numpy() < 0.5
            hit += int((removed & pasted).sum())
            union += int((removed | pasted).sum())
    assert float(composite["object_iou"]) == pytest.approx(hit / union, abs=0.02)


def _load(script: str):
    spec = importlib.util.spec_from_file_location(script, EXPERIMENT / f"{script}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_summarize_pools_a_sweeps_training_seeds(tmp_path: Path) -> None:
    """A training sweep's checkpoints of one setting (run folders ``filter=unet,seed=N``) are one model whose
    runs are its training seeds × the occluder seeds: recall over all of them, gains paired over their mean hit
    rate, the clean frames' one run per training seed as the base of the recovered share."""
    summarize = _load("summarize")
    rng = np.random.default_rng(0)
    ranks: dict[tuple[str, str, int, int], np.ndarray] = {}
    pair = tmp_path / "eval" / "day_left-night_right"
    job = 0
    for sweep, hit_rate in (("m1-clean-none", 0.9), ("m1-occluded-none", 0.4), ("m1-occluded-oracle", 0.7)):
        condition, mask = sweep.split("-")[1:]
        for train in (0, 1):
            for occluder in (0,) if condition == "clean" else (0, 1, 2):
                found = np.where(rng.random(60) < hit_rate, 0, rng.integers(1, 30, 60))
                ranks[condition, mask, train, occluder] = found
                folder = pair / sweep / str(job)
                folder.mkdir(parents=True)
                job += 1
                name = "gardens_point day_left→night_right ±2"
                if condition != "clean":
                    name += f" + CamVid 20% seed {occluder}"
                checkpoint = tmp_path / "runs" / f"filter=unet,seed={train},threads=1" / "checkpoints" / "best.ckpt"
                result = {"status": "ok", "checkpoint": str(checkpoint), "aggregator": "sral", "set": name}
                result |= {"queries": 60, "test/R@1": 100 * np.mean(found == 0), "test/R@5": 100 * np.mean(found < 5)}
                (folder / "eval.json").write_text(json.dumps(result))
                np.save(folder / "ranks.npy", found)
    runs = summarize.collect(tmp_path)
    rows = {
        (r["condition"], r["mask"]): r for r in summarize.rows("day_left-night_right", runs["day_left-night_right"])
    }
    assert set(rows) == {("clean", "none"), ("occluded", "none"), ("occluded", "oracle")}
    assert {r["model"] for r in rows.values()} == {"filter=unet"}

    def mean_r1(condition: str, mask: str) -> float:
        return float(np.mean([100 * np.mean(r == 0) for k, r in ranks.items() if k[:2] == (condition, mask)]))

    for (condition, mask), row in rows.items():
        assert (row["models"], row["runs"]) == (2, 2 if condition == "clean" else 6)
        assert row["r1"] == pytest.approx(mean_r1(condition, mask), abs=0.01)
    oracle = rows["occluded", "oracle"]
    assert oracle["gain"] == pytest.approx(mean_r1("occluded", "oracle") - mean_r1("occluded", "none"), abs=0.02)
    clean, occluded = mean_r1("clean", "none"), mean_r1("occluded", "none")
    assert oracle["recovered"] == pytest.approx(
        (mean_r1("occluded", "oracle") - occluded) / (clean - occluded), abs=0.002
    )
    assert "| day_left → night_right | SRAL, SynthCity, trained with its student's mask (filter=unet) | 20 % |" in (
        "\n".join(summarize.summary(list(rows.values())))
    )


def test_mask_iou_scores_a_confusion_of_objects_and_the_rest() -> None:
    """mask_iou.py's scores of a (trainId × [removed, kept, other]) confusion, by hand: the moving classes are
    the objects, every other labelled pixel is one to keep (sky too)."""
    module = _load("mask_iou")
    counts = np.zeros((19, 3), dtype=np.int64)
    car, person, building, sky = (module.TRAIN_ID_NAMES.index(n) for n in ("car", "person", "building", "sky"))
    counts[car] = [30, 10, 0]  # 30 car pixels removed, 10 kept
    counts[person] = [5, 5, 0]
    counts[building] = [6, 84, 0]
    counts[sky] = [10, 0, 0]
    scores = module.object_scores(counts)
    assert scores == {"object_iou": round(35 / (50 + 16), 4), "objects_removed": 0.7, "rest_removed": 0.16}


def test_summarize_refuses_ranks_that_contradict_eval_json_and_a_cell_short_of_a_draw(tmp_path: Path) -> None:
    """Float ranks that eval.json does not give read as "R@1 41.0 ± 51.1"; a stopped sweep's cell with 2 of 3
    occluder draws was averaged with no word. Each is one line."""
    from semvpr.core.errors import SemvprError

    summarize = _load("summarize")
    pair = tmp_path / "eval" / "day_left-night_right"

    def job(sweep: str, num: int, draw: int, ranks: np.ndarray) -> Path:
        folder = pair / sweep / str(num)
        folder.mkdir(parents=True)
        result = {"status": "ok", "checkpoint": "none", "aggregator": "netvlad", "queries": len(ranks)}
        result |= {"set": f"gardens_point day_left→night_right ±2 + CamVid 20% seed {draw}"}
        result |= {"test/R@1": 100 * np.mean(ranks == 0), "test/R@5": 100 * np.mean((ranks >= 0) & (ranks < 5))}
        (folder / "eval.json").write_text(json.dumps(result))
        np.save(folder / "ranks.npy", ranks)
        return folder

    ranks = np.array([0, 3, 0, 7, 1, 0])
    for draw in (0, 1, 2):
        job("m0-occluded-none", draw, draw, ranks)
    for draw in (0, 1):
        job("m0-occluded-oracle", draw, draw, ranks)
    with pytest.raises(
        SemvprError, match=r"oracle 20 holds occluder seeds \[0, 1\], the pair's other cells \[0, 1, 2\]"
    ):
        summarize.collect(tmp_path)
    folder = job("m0-occluded-oracle", 2, 2, ranks)
    assert summarize.collect(tmp_path)
    np.save(folder / "ranks.npy", ranks.astype(float) + 0.5)
    with pytest.raises(SemvprError, match=r"ranks\.npy: not 6 whole-number ranks \(float64\)"):
        summarize.collect(tmp_path)
    np.save(folder / "ranks.npy", np.zeros(6, dtype=int))
    with pytest.raises(SemvprError, match=r"ranks\.npy does not give eval\.json's R@1"):
        summarize.collect(tmp_path)
