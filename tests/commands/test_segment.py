"""`python -m semvpr.segment` end to end on a tiny CamVid, and its saved teacher used as teacher.checkpoint."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from semvpr.config.schema import typed
from semvpr.core.errors import SemvprError, one_line
from semvpr.models.masks import TeacherMask
from semvpr.models.teacher import TeacherSpec
from semvpr.segment import run, summary
from semvpr.segmentation.scoring import teacher_outputs
from semvpr.segmentation.training import build_teacher
from tests.camvid_fixture import write_camvid
from tests.helpers import CONF_DIR, REPO

TINY = [
    "seg.image_size=[32,48]",
    "seg.num_workers=0",
    "num_figure_images=2",
    "eval_batch_size=2",
    "teacher.model.embed_dim=16",
    "teacher.model.depths=[1,1,1,1]",
    "teacher.model.num_heads=[1,1,2,2]",
    "teacher.model.window_size=4",
    "teacher.model.hidden_dim=32",
    "teacher.model.num_attention_heads=2",
    "teacher.model.encoder_layers=1",
    "teacher.model.decoder_layers=2",
    "teacher.model.num_queries=8",
    "teacher.model.train_num_points=256",
    "teacher.train.epochs=1",
    "teacher.train.batch_size=2",
    "teacher.train.num_workers=0",
    "teacher.train.warmup_steps=1",
    "teacher.predict_batch_size=4",
    "student.epochs=2",
    "student.width=8",
    "student.batch_size=4",
    "student.num_workers=0",
]


def segment_config(*overrides: str) -> DictConfig:
    """The segment command's config, shrunk to seconds."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="segment", overrides=[*TINY, *overrides])


@pytest.fixture(scope="module")
def segment_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, DictConfig]:
    """One complete tiny run (teacher, pseudo-labels, EfficientNet-Lite0 and random-init VGG16 students)."""
    tmp = tmp_path_factory.mktemp("segment")
    cfg = segment_config(
        f"seg.root={write_camvid(tmp / 'camvid')}",
        f"paths.cache_dir={tmp / 'cache'}",
        "+backbone@backbones.vgg16=vgg16",
    )
    run(cfg, tmp / "run")
    return tmp / "run", cfg


def test_run_writes_results_figure_logs_and_teacher(segment_run: tuple[Path, DictConfig]) -> None:
    run_dir, _ = segment_run
    results = json.loads((run_dir / "results.json").read_text())
    assert set(results) >= {"teacher", "student_efficientnet_lite0", "student_vgg16", "dataset", "pseudo_labels"}
    assert results["dataset"]["train"] == 6 and results["dataset"]["test"] == 3
    assert len(results["dataset"]["classes"]) == 11 and "rider" in results["dataset"]["classes"]
    teacher = results["teacher"]
    assert 0.0 <= teacher["miou"] <= 1.0 and 0.0 <= teacher["dynamic_iou"] <= 1.0 and teacher["train_s"] > 0
    assert set(teacher["class_iou"]) == set(results["dataset"]["classes"])
    assert 0.0 <= teacher["val"]["miou"] <= 1.0 and "sky_removed" in teacher
    for name in ("student_efficientnet_lite0", "student_vgg16"):
        student = results[name]
        assert 0.0 <= student["dynamic_iou"] <= 1.0 and student["train_s"] > 0 and "static_removed" in student["val"]
    assert (run_dir / "figure_masks.png").stat().st_size > 10_000
    assert list((run_dir / "csv").rglob("metrics.csv")) and list((run_dir / "tensorboard").rglob("events.*"))
    assert {p.name for p in (run_dir / "teacher").iterdir()} >= {
        "config.json",
        "model.safetensors",
        "preprocessor_config.json",
    }
    assert not list(run_dir.glob(".*tmp*"))  # results and teacher were renamed into place


def test_score_test_false_scores_val_only(
    segment_run: tuple[Path, DictConfig], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Choosing settings: with score_test=false no model sees a test image; the top-level numbers are val's."""
    import semvpr.segment as segment

    _, cfg = segment_run
    seen: list[int] = []
    for name in ("score_teacher", "score_student"):
        real = getattr(segment, name)

        def spy(*args, real=real, **kwargs):
            seen.append(len(next(a for a in args if hasattr(a, "images")).images))
            return real(*args, **kwargs)

        monkeypatch.setattr(segment, name, spy)
    results = run(OmegaConf.merge(cfg, {"score_test": False}), tmp_path / "val-only")
    assert seen and set(seen) == {len(instantiate(cfg.seg.val))} != {len(instantiate(cfg.seg.test))}
    assert results["scored_on"].startswith("val only") and "test" not in results["teacher"]
    assert results["teacher"]["dynamic_iou"] == results["teacher"]["val"]["dynamic_iou"]
    assert (
        results["student_efficientnet_lite0"]["dynamic_iou"]
        == results["student_efficientnet_lite0"]["val"]["dynamic_iou"]
    )


def test_run_saves_each_student_where_eval_reads_it_and_says_where(
    segment_run: tuple[Path, DictConfig], tmp_path: Path
) -> None:
    """<run>/student_<backbone>: safetensors and student.json, named in results.json and the summary line;
    it loads over its own backbone with the trained student's weights (and is refused over another)."""
    from safetensors.torch import load_file

    from semvpr.config.build import build_backbone
    from semvpr.models.student import load_student
    from semvpr.models.teacher_folder import read_teacher_record

    run_dir, cfg = segment_run
    results = json.loads((run_dir / "results.json").read_text())
    line = summary(results, run_dir)
    assert line["teacher/checkpoint"] == str(run_dir / "teacher")
    backbones = {name: build_backbone(node, int(cfg.seed)).eval() for name, node in cfg.backbones.items()}
    for name, backbone in backbones.items():
        folder = run_dir / f"student_{name}"
        assert results[f"student_{name}"]["checkpoint"] == line[f"student_{name}/checkpoint"] == str(folder)
        assert {p.name for p in folder.iterdir()} == {"model.safetensors", "student.json"}
        student = load_student(folder, backbone)
        stored = load_file(folder / "model.safetensors")
        assert stored.keys() == student.state_dict().keys()
        assert student.head.weight.shape[1] == cfg.student.width
        assert (student.trained_on.name, student.trained_on.domain) == ("camvid", "real")
    with pytest.raises(SemvprError, match=r"decodes the frozen trunk of vgg16 .* this model's is EfficientNetLite0"):
        load_student(run_dir / "student_vgg16", backbones["efficientnet_lite0"])
    record = read_teacher_record(run_dir / "teacher")
    assert record["image_size"] == [32, 48] and record["trained_on"].name == "camvid"


def test_saved_teacher_is_a_checkpoint_with_equal_predictions(
    segment_run: tuple[Path, DictConfig], tmp_path: Path
) -> None:
    run_dir, cfg = segment_run
    trained = build_teacher(
        typed(TeacherSpec, cfg.teacher, "teacher"),
        instantiate(cfg.seg.train),
        instantiate(cfg.seg.val),
        cfg.paths.cache_dir,
    )
    loaded = build_teacher(
        typed(TeacherSpec, OmegaConf.merge(cfg.teacher, {"checkpoint": str(run_dir / "teacher")}), "teacher"),
        None,
        None,
        tmp_path / "other-cache",
    )
    assert loaded.teacher_key.startswith("pretrained-") and not (tmp_path / "other-cache").exists()
    assert loaded.inference_size == (32, 48) and loaded.trained_on.name == "camvid"  # from its semvpr.json
    images = torch.rand(2, 3, 32, 48)
    assert torch.equal(loaded.predict_train_ids(images), trained.predict_train_ids(images))
    assert torch.equal(loaded.class_prob(images), trained.class_prob(images))
    # one-pass scoring outputs = the teacher's own post-processing at the input size (binary filter's input)
    mask = TeacherMask(loaded, list(cfg.teacher.static_classes))
    ids, prob = teacher_outputs(loaded, images, (32, 48), list(cfg.teacher.static_classes))
    assert torch.equal(ids, loaded.predict_train_ids(images))
    torch.testing.assert_close(prob, mask.static_prob(mask(images, [], None)), rtol=1e-5, atol=1e-5)


def test_a_given_teacher_is_scored_and_distilled_not_trained(
    segment_run: tuple[Path, DictConfig], tmp_path: Path
) -> None:
    """teacher.checkpoint=<a saved teacher>: the run scores that teacher (the trained run's numbers), labels the
    train images with it and trains the students; nothing is trained for the teacher, nothing copied."""
    run_dir, cfg = segment_run
    trained = json.loads((run_dir / "results.json").read_text())
    given = OmegaConf.merge(
        cfg, {"teacher": {"checkpoint": str(run_dir / "teacher")}, "paths": {"cache_dir": str(tmp_path / "cache")}}
    )
    results = run(given, tmp_path / "run")
    assert results["teacher"]["checkpoint"] == str(run_dir / "teacher") and results["teacher"]["train_s"] is None
    same = [json.dumps(r["teacher"]["val"], sort_keys=True) for r in (results, trained)]  # NaN-aware
    assert same[0] == same[1]
    assert (results["teacher"]["dynamic_iou"], results["teacher"]["miou"]) == (  # test's, at the top level
        trained["teacher"]["dynamic_iou"],
        trained["teacher"]["miou"],
    )
    assert not list((tmp_path / "cache").glob("teacher-*")) and not (tmp_path / "run" / "teacher").exists()
    student = results["student_efficientnet_lite0"]
    assert student["train_s"] > 0 and (tmp_path / "run" / "student_efficientnet_lite0" / "model.safetensors").is_file()
    line = summary(results, tmp_path / "run")  # the last stdout line: no training time for a teacher not trained
    assert line["teacher/checkpoint"] == str(run_dir / "teacher") and "teacher/train_s" not in line
    assert line["teacher/dynamic_iou"] == round(trained["teacher"]["dynamic_iou"], 3)


def test_unset_root_is_a_user_error(tmp_path: Path) -> None:
    with pytest.raises(SemvprError, match=r"seg\.root is not set"):
        run(segment_config(f"paths.cache_dir={tmp_path}"), tmp_path / "run")


@pytest.mark.parametrize(
    ("override", "line"),
    [
        ("backbones.efficientnet_lite0.stage=stage9", r"^backbone\.stage='stage9' is not one of"),
        ("backbones.efficientnet_lite0.weights=/nonexistent.pth", r"nonexistent\.pth"),
        # torch's TypeError (an int for a path) once the trunk was built; train's backbone.weights was checked
        ("backbones.efficientnet_lite0.weights=3", r"^backbones\.efficientnet_lite0\.weights=3 is not a path"),
    ],
)
def test_a_student_trunk_it_cannot_build_is_refused_before_the_teacher_trains(
    tmp_path: Path, override: str, line: str
) -> None:
    """The trunks were built after the teacher had trained and labelled the set (an hour on CamVid)."""
    cfg = segment_config(
        f"seg.root={write_camvid(tmp_path / 'camvid')}", f"paths.cache_dir={tmp_path / 'cache'}", override
    )
    with pytest.raises(SemvprError, match=line):
        run(cfg, tmp_path / "run")
    assert not any(p.name.startswith("teacher-") for p in (tmp_path / "cache").glob("*"))


def test_worker_wrapped_error_prints_its_own_line() -> None:
    wrapped = SemvprError(
        "Caught SemvprError in DataLoader worker process 0.\nOriginal Traceback (most recent "
        'call last):\n  File "x.py", line 1\nsemvpr.core.errors.SemvprError: image a.jpg is corrupt\n'
    )
    assert one_line(wrapped) == "image a.jpg is corrupt"
    assert one_line(SemvprError("plain")) == "plain"


def test_cli_bad_root_one_line_exit_2(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1"}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.segment",
            f"seg.root={tmp_path / 'nowhere'}",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"semvpr: error: CamVid root {tmp_path / 'nowhere'} is not a directory; set seg.root to the folder "
        "holding train/, trainannot/ and train.txt (SegNet layout)"
    ]


@pytest.mark.slow
def test_vpr_run_uses_the_saved_teacher(segment_run: tuple[Path, DictConfig], tmp_path: Path) -> None:
    from semvpr.train import run_job
    from tests.helpers import tiny_config

    run_dir, _ = segment_run
    cfg = tiny_config(
        tmp_path / "cache",
        "filter=mask2former",
        f"teacher.checkpoint={run_dir / 'teacher'}",
        "+trainer.fast_dev_run=true",
    )
    metrics = run_job(cfg, tmp_path / "vpr")
    assert metrics["status"] == "ok" and 0.0 <= metrics["test/R@1"] <= 100.0
    assert not list((tmp_path / "cache").glob("teacher-*"))  # nothing trained: the saved teacher was used


def test_paired_masks_scores_each_saved_source_as_the_run_did(segment_run: tuple[Path, DictConfig]) -> None:
    """experiments/camvid-semantic/paired_masks.py on the run's saved teacher and student: each one's val
    dynamic IoU, pooled from its frame-by-frame counts, is the run's own val score, and the paired interval
    holds the observed difference."""
    run_dir, cfg = segment_run
    results = json.loads((run_dir / "results.json").read_text())
    size = ",".join(str(v) for v in cfg.seg.image_size)
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "experiments/camvid-semantic/paired_masks.py"),
            str(run_dir / "teacher"),
            str(run_dir / "student_efficientnet_lite0"),
            "--root",
            str(cfg.seg.root),
            "--resamples",
            "200",
            f"seg.image_size=[{size}]",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = dict(field.split("=") for field in proc.stdout.strip().splitlines()[-1].split())
    assert line["split"] == "val" and int(line["frames"]) == results["dataset"]["val"]
    assert float(line["a"]) == pytest.approx(results["teacher"]["val"]["dynamic_iou"], abs=1e-4)
    assert float(line["b"]) == pytest.approx(results["student_efficientnet_lite0"]["val"]["dynamic_iou"], abs=1e-4)
    assert float(line["low"]) <= float(line["diff"]) <= float(line["high"])


def test_a_sigterm_while_the_teacher_trains_is_one_line_exit_2(tmp_path: Path) -> None:
    """Lightning ends the teacher's fit on SIGTERM by a SystemExit of code None: segment exited 0 having done
    nothing (a scheduler records a finished job). It is a stop: one line, exit 2, no teacher in the cache."""
    root = write_camvid(tmp_path / "camvid")
    overrides = [*TINY, "teacher.train.epochs=100000", "threads=1"]
    cmd = [sys.executable, "-m", "semvpr.segment", f"seg.root={root}", *overrides]
    cmd += [f"paths.cache_dir={tmp_path / 'cache'}", f"hydra.run.dir={tmp_path / 'run'}"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1"}
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    try:
        lines = []
        for line in proc.stderr:  # type: ignore[union-attr]
            lines.append(line)
            if line.startswith("semvpr: teacher: epoch 2/"):
                proc.send_signal(signal.SIGTERM)
                break
        rest = proc.communicate(timeout=600)[1]
    finally:
        proc.kill()
    assert proc.returncode == 2, "".join(lines) + rest
    assert rest.strip().splitlines()[-1] == "semvpr: error: stopped by SIGTERM"
    assert not list((tmp_path / "cache").glob("teacher-*")) and not (tmp_path / "run" / "results.json").exists()
