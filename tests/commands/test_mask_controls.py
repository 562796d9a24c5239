"""Mask controls at evaluation: where the mask applies (the other side's descriptors are the unmasked ones),
controls kept apart in the descriptor cache, a checkpoint's recorded control and the invocation's in its
place, and an evaluation multirun over controls: eval.json, hits.npz and the table name each one."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers import (
    FRAME_SIZE,
    REPO,
    config,
    frame_images,
    tiny_config,
    write_checkpoint,
    write_frames,
    write_student_dir,
    write_teacher_dir,
)

SIZE = [f"data.image_size=[{FRAME_SIZE[0]},{FRAME_SIZE[1]}]", "data.num_workers=0"]


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A frame-aligned set, a checkpoint trained without a mask, one trained with a student mask under a
    shuffled control, and a student directory whose mask keeps some cells and drops others."""
    from semvpr.config.build import build_backbone

    tmp = tmp_path_factory.mktemp("controls")
    frames = write_frames(tmp / "frames", {"day": list(range(8)), "night": list(range(8))})
    paths = {"frames": frames, "plain": tmp / "plain.ckpt", "shuffled": tmp / "shuffled.ckpt"}
    write_checkpoint(tiny_config(tmp / "cache", "filter=attention"), paths["plain"])
    controlled = tiny_config(tmp / "cache", "filter=unet", "mask.control=shuffled", "mask.control_seed=5")
    write_checkpoint(controlled, paths["shuffled"])
    backbone = build_backbone(tiny_config(tmp / "cache").backbone, 0).eval()
    paths["student"] = write_student_dir(
        tmp / "seg" / "student_efficientnet_lite0", backbone, frame_images(frames, "day")
    )
    return paths


def frames_args(world: dict[str, Path]) -> list[str]:
    return ["data=frames", f"data.root={world['frames']}", "data.database=day", "data.queries=night", *SIZE]


def student(world: dict[str, Path]) -> list[str]:
    return ["mask=student", f"student.checkpoint={world['student']}"]


def load(world: dict[str, Path], ckpt: str, cache: Path, *overrides: str):
    from semvpr.config.restore import load_retriever

    args = [*frames_args(world), f"+ckpt={world[ckpt]}", f"paths.cache_dir={cache}", *overrides]
    return load_retriever(config(*args, config_name="eval"), {o.split("=", 1)[0].lstrip("+") for o in overrides})


def described(world: dict[str, Path], cache: Path, *overrides: str) -> tuple[np.ndarray, np.ndarray]:
    """Database and query descriptors of the frames set under the plain checkpoint, at one thread."""
    from semvpr.config.build import build_places
    from semvpr.config.plan import data_settings
    from semvpr.eval import describe

    retriever, merged = load(world, "plain", cache, *overrides)
    test = build_places(data_settings(merged), ("test",))["test"]
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return tuple(np.array(d) for d in describe(retriever, merged, test))  # type: ignore[return-value]
    finally:
        torch.set_num_threads(before)


def test_a_mask_on_one_side_leaves_the_other_sides_descriptors_unmasked(world: dict[str, Path], tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    plain_db, plain_q = described(world, cache, "mask=none")
    both_db, both_q = described(world, cache, *student(world))
    assert not np.allclose(both_db, plain_db) and not np.allclose(both_q, plain_q)  # the mask removes cells
    db_only = described(world, cache, *student(world), "mask.apply=database")
    assert np.array_equal(db_only[0], both_db) and np.array_equal(db_only[1], plain_q)
    q_only = described(world, cache, *student(world), "mask.apply=queries")
    assert np.array_equal(q_only[0], plain_db) and np.array_equal(q_only[1], both_q)


def test_each_control_is_another_descriptor_cache(world: dict[str, Path], tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    seen = {"own": described(world, cache, *student(world))[0]}
    for control in ("objects", "sky", "random", "shuffled"):
        seen[control] = described(world, cache, *student(world), f"mask.control={control}")[0]
    seen["random 1"] = described(world, cache, *student(world), "mask.control=random", "mask.control_seed=1")[0]
    assert len(list(cache.glob("descriptors-*"))) == 2 * len(seen)  # each setting its own, on both sides
    # The drawn controls give other descriptors than the source's mask (objects and sky may not: an untrained
    # student's sky or objects alone may never make most of a cell).
    drawn = [seen[k].tobytes() for k in ("own", "random", "shuffled", "random 1")]
    assert len(set(drawn)) == len(drawn)


def test_every_control_takes_a_teacher_mask(world: dict[str, Path], tmp_path: Path) -> None:
    """The teacher's mask (it reads the images at its own size) under each control: one mask pass per weighting,
    none for a control."""
    from semvpr.retrieval.controls import CONTROLS

    teacher = ["mask=teacher", f"teacher.checkpoint={write_teacher_dir(tmp_path / 'teacher')}"]
    cache = tmp_path / "cache"
    for control in CONTROLS:
        db, q = described(world, cache, *teacher, f"mask.control={control}")
        assert np.isfinite(db).all() and np.isfinite(q).all()
    assert len(list(cache.glob("descriptors-*"))) == 2 * len(CONTROLS)
    assert len(list(cache.glob("masks-*"))) == 2  # binary (none, random, shuffled) and pooled classes (objects, sky)


def test_a_checkpoint_records_its_control_and_the_command_line_replaces_it(
    world: dict[str, Path], tmp_path: Path
) -> None:
    record = torch.load(world["shuffled"], weights_only=True)["hyper_parameters"]
    assert {k: record["config"]["mask"][k] for k in ("control", "apply", "control_seed")} == {
        "control": "shuffled",
        "apply": "both",
        "control_seed": 5,
    }
    _, merged = load(world, "shuffled", tmp_path)
    assert (merged.mask.control, merged.mask.apply, merged.mask.control_seed) == ("shuffled", "both", 5)
    _, merged = load(world, "shuffled", tmp_path, "mask.control=sky", "mask.apply=queries")
    assert (merged.mask.control, merged.mask.apply, merged.mask.control_seed) == ("sky", "queries", 5)
    # A checkpoint recorded before the controls existed reads as the source's own mask on both sides.
    data = torch.load(world["shuffled"], weights_only=True)
    for key in ("control", "apply", "control_seed"):
        del data["hyper_parameters"]["config"]["mask"][key]
    torch.save(data, tmp_path / "before.ckpt")
    world = {**world, "before": tmp_path / "before.ckpt"}
    _, merged = load(world, "before", tmp_path)
    assert (merged.mask.control, merged.mask.apply, merged.mask.control_seed) == ("none", "both", 0)


def test_localize_refuses_a_control(world: dict[str, Path], tmp_path: Path) -> None:
    from semvpr.config.restore import load_retriever
    from semvpr.core.errors import SemvprError

    cfg = config(*frames_args(world), f"+ckpt={world['shuffled']}", f"paths.cache_dir={tmp_path}", config_name="eval")
    with pytest.raises(SemvprError, match=r"^mask\.control=shuffled mask\.apply=both is a control of an evaluation"):
        load_retriever(cfg, set(), new_images=True)


def test_the_hits_eval_writes_give_its_recalls(world: dict[str, Path], tmp_path: Path) -> None:
    """hits.npz's columns (here on a database of 8 frames: fewer than 20 retrieved) average to eval.json's R@N."""
    from semvpr.eval import evaluate_checkpoint, query_hits

    overrides = [*student(world), "mask.control=random"]
    cfg = config(
        *frames_args(world), f"+ckpt={world['plain']}", f"paths.cache_dir={tmp_path}", *overrides, config_name="eval"
    )
    result = evaluate_checkpoint(cfg, {o.split("=", 1)[0] for o in overrides})
    hits = query_hits(np.asarray(result["ranks"]), result["top"])
    assert hits["top"].shape == (8, 8) and hits["hits"].shape == (8, 4)
    for i, n in enumerate(hits["ns"]):
        assert round(100 * hits["hits"][:, i].mean(), 2) == result[f"test/R@{n}"]


@pytest.mark.slow
def test_an_eval_multirun_over_controls_writes_and_names_each(world: dict[str, Path], tmp_path: Path) -> None:
    """Two jobs through the CLI: eval.json records the control, hits.npz gives eval.json's recalls, and the
    table's row names the control."""
    (tmp_path / "cwd").mkdir()
    sweep = tmp_path / "sweep"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.eval",
            "-m",
            f"ckpt={world['plain']}",
            *frames_args(world),
            *student(world),
            "mask.control=none,random",
            "mask.apply=database",
            f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.sweep.dir={sweep}",
            "threads=1",
        ],
        cwd=tmp_path / "cwd",
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    for job, control in (("0", "none"), ("1", "random")):
        result = json.loads((sweep / job / "eval.json").read_text())
        assert (result["mask_control"], result["mask_apply"], result["mask_control_seed"]) == (control, "database", 0)
        with np.load(sweep / job / "hits.npz") as hits:
            assert hits["ns"].tolist() == [1, 5, 10, 20]
            assert hits["hits"].shape == (result["queries"], 4) and hits["hits"].dtype == bool
            assert hits["top"].shape == (result["queries"], min(20, result["database"]))
            for i, n in enumerate(hits["ns"]):
                assert abs(100 * hits["hits"][:, i].mean() - result[f"test/R@{n}"]) < 0.006
                # Query frame q's positives are the database frames within ±2 (data.frame_window).
                near = np.abs(hits["top"][:, :n] - np.arange(result["queries"])[:, None]) <= 2
                assert np.array_equal(near.any(1), hits["hits"][:, i])
    with open(sweep / "results.csv", newline="") as fh:
        sources = [row["source"] for row in csv.DictReader(fh) if row["data"] != "published"]
    assert "control=random (seed 0), on the database only" in sources[1]
    assert "control=" not in sources[0] and "on the database only" in sources[0]


def test_a_training_run_takes_a_control_and_records_it(tmp_path: Path) -> None:
    from semvpr.train import run_job

    cfg = tiny_config(
        tmp_path / "cache",
        "aggregator=gem",
        "mask=oracle",
        "mask.control=sky",
        "mask.apply=queries",
        "+trainer.fast_dev_run=true",
    )
    metrics = run_job(cfg, tmp_path / "run")
    assert (metrics["mask"], metrics["mask_control"], metrics["mask_apply"]) == ("oracle", "sky", "queries")
    assert 0.0 <= metrics["test/R@1"] <= 100.0
    maps = np.load(tmp_path / "run" / "maps.npz")  # the test queries' masks: the sky control's, binary
    assert set(np.unique(maps["oracle"])) <= {0.0, 1.0}
