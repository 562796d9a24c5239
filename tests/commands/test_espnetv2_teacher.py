"""``teacher=espnetv2 teacher.checkpoint=FILE`` wherever a teacher is used: as a teacher sees images (the
authors' preprocessing, channels mapped to Cityscapes trainIds by name), in training (pseudo-labels, SRAL's
semantic init, the student), in the mask swap at evaluation, in ``semvpr.segment`` (scored and distilled, never
trained) and in ``semvpr.label``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from semvpr.config.schema import typed
from semvpr.core.errors import SemvprError
from semvpr.data.classes import IGNORE, TRAIN_ID_COLOURS
from semvpr.models.teacher import TeacherSpec, TeacherTraining
from semvpr.models.teacher_folder import teacher_architecture
from tests.camvid_fixture import write_camvid
from tests.helpers import CONF_DIR, REPO, make_images, tiny_config, write_espnetv2

SIZE = (64, 128)


@pytest.fixture(scope="module")
def espnet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_espnetv2(tmp_path_factory.mktemp("espnetv2") / "espnetv2_s_0.5_city_1024x512.pth")


def spec(path: Path, **values) -> TeacherSpec:
    return TeacherSpec(
        name="espnetv2", checkpoint=str(path), inference_size=SIZE, train=TeacherTraining(bf16=False), **values
    )


def test_the_teacher_sees_images_as_the_authors_test_script_does(espnet: Path) -> None:
    teacher = teacher_architecture(spec(espnet))
    image = torch.rand(2, 3, 45, 70, generator=torch.Generator().manual_seed(0))
    # By hand: ImageNet normalisation, an antialiased bilinear resize to the inference size, the network's
    # softmax resized back, argmax; channel c is trainId c, the 20th (background) none.
    mean, std = (
        torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1),
        torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1),
    )
    x = F.interpolate((image - mean) / std, SIZE, mode="bilinear", align_corners=False, antialias=True)
    with torch.no_grad():
        prob = teacher.model(x).softmax(1)
    expected = F.interpolate(prob, (45, 70), mode="bilinear", align_corners=False).argmax(1)
    expected[expected == 19] = IGNORE
    assert torch.equal(teacher.predict_train_ids(image), expected)
    # The class probabilities are the softmax's resized back, background left out (so they sum to 1 - p(background)),
    # whether the images are smaller than the inference size (the scores resized first) or larger.
    for h, w in ((45, 70), (80, 150)):
        image = torch.rand(2, 3, h, w, generator=torch.Generator().manual_seed(h))
        x = F.interpolate((image - mean) / std, SIZE, mode="bilinear", align_corners=False, antialias=True)
        with torch.no_grad():
            prob = F.interpolate(teacher.model(x).softmax(1), (h, w), mode="bilinear", align_corners=False)
        class_prob = teacher.class_prob(image)
        assert class_prob.shape == (2, 19, h, w)
        assert (class_prob - prob[:, :19]).abs().max() < 1e-6
        assert torch.allclose(class_prob.sum(1), 1 - prob[:, 19], atol=1e-5)
    assert teacher.trained_on.domain == "real" and teacher.teacher_key.startswith("espnetv2-")
    # Another file is another teacher: its labels are cached apart.
    other = teacher_architecture(spec(write_espnetv2(espnet.parent / "other.pth", seed=1)))
    assert other.teacher_key != teacher.teacher_key


def test_it_labels_predict_batch_size_images_per_pass_whatever_batch_it_is_given(espnet: Path) -> None:
    teacher = teacher_architecture(spec(espnet, predict_batch_size=2))
    seen: list[int] = []
    teacher.model.register_forward_pre_hook(lambda _, args: seen.append(len(args[0])))
    images = torch.rand(5, 3, 30, 40, generator=torch.Generator().manual_seed(1))
    parts = teacher.class_prob(images)
    assert seen == [2, 2, 1]
    whole = torch.cat([teacher.class_prob(images[i : i + 1]) for i in range(5)])
    assert torch.allclose(parts, whole, atol=1e-5)


def test_without_a_file_it_is_one_line_naming_the_setting(tmp_path: Path) -> None:
    with pytest.raises(SemvprError, match=r"teacher=espnetv2 needs teacher.checkpoint=FILE"):
        teacher_architecture(TeacherSpec(name="espnetv2"))
    with pytest.raises(SemvprError, match=r"teacher.name='segformer' is not one of"):
        typed(TeacherSpec, {"name": "segformer"}, "teacher")
    with pytest.raises(SemvprError, match=r"not found"):
        teacher_architecture(spec(tmp_path / "absent.pth"))


def test_a_training_run_uses_it_for_labels_init_and_student(espnet: Path, tmp_path: Path) -> None:
    from semvpr.train import run_job

    overrides = ["teacher=espnetv2", f"teacher.checkpoint={espnet}", f"teacher.inference_size=[{SIZE[0]},{SIZE[1]}]"]
    # SRAL's semantic init and the student, both from the teacher's pseudo-labels (its mask: the swap below).
    cfg = tiny_config(tmp_path / "cache", "filter=unet", *overrides, "+trainer.fast_dev_run=true")
    metrics = run_job(cfg, tmp_path / "run")
    assert metrics["filter"] == "unet" and 0.0 <= metrics["test/R@1"] <= 100.0
    # Pseudo-labels and the student come from this teacher: keyed by its file, not by the embedded teacher.
    labels = [p.name for p in (tmp_path / "cache").iterdir() if p.name.startswith("labels-")]
    assert labels and not any(p.name.startswith("teacher-") for p in (tmp_path / "cache").iterdir())


def test_segment_scores_and_distils_it_without_training_it(espnet: Path, tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir

    from semvpr.segment import run
    from tests.commands.test_segment import TINY

    # The embedded teacher's sizes and training aside: this teacher has neither.
    tiny = [o for o in TINY if not o.startswith(("teacher.model.", "teacher.train."))]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(
            config_name="segment",
            overrides=[
                *tiny,
                f"seg.root={write_camvid(tmp_path / 'camvid')}",
                f"paths.cache_dir={tmp_path / 'cache'}",
                "teacher=espnetv2",
                f"teacher.checkpoint={espnet}",
                f"teacher.inference_size=[{SIZE[0]},{SIZE[1]}]",
            ],
        )
    run(cfg, tmp_path / "run")
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    assert results["teacher"]["checkpoint"] == str(espnet) and results["teacher"]["train_s"] is None
    assert 0.0 <= results["teacher"]["miou"] <= 1.0 and "class_iou" in results["teacher"]
    assert 0.0 <= results["student_efficientnet_lite0"]["dynamic_iou"] <= 1.0
    assert not (tmp_path / "run" / "teacher").exists()  # a given teacher stays where it is


def test_label_writes_train_ids_and_the_static_mask_for_a_folder(espnet: Path, tmp_path: Path) -> None:
    images = tmp_path / "images"
    make_images(images / "walk", n=3)
    (tmp_path / "cwd").mkdir()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "semvpr.label",
            f"images={images}",
            "teacher=espnetv2",
            f"teacher.checkpoint={espnet}",
            f"teacher.inference_size=[{SIZE[0]},{SIZE[1]}]",
            f"hydra.run.dir={tmp_path / 'run'}",
            "threads=1",
        ],
        cwd=tmp_path / "cwd",
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    record = json.loads((tmp_path / "run" / "label.json").read_text())
    assert record["images"] == 3 and record["teacher"] == "espnetv2"
    teacher = teacher_architecture(spec(espnet))
    for row in record["per_image"]:
        source = images / row["image"]
        ids_png = Image.open(tmp_path / "run" / "train_ids" / Path(row["image"]).with_suffix(".png"))
        static_png = np.asarray(Image.open(tmp_path / "run" / "static" / Path(row["image"]).with_suffix(".png")))
        original = np.asarray(Image.open(source).convert("RGB"))
        assert ids_png.mode == "P" and ids_png.size == (original.shape[1], original.shape[0])
        assert ids_png.getpalette()[:3] == list(TRAIN_ID_COLOURS[0])
        image = torch.from_numpy(original.copy()).permute(2, 0, 1).float()[None] / 255
        assert np.array_equal(np.asarray(ids_png), teacher.predict_train_ids(image)[0].numpy())
        assert set(np.unique(static_png)) <= {0, 255}
        assert row["removed"] == pytest.approx(float((static_png == 0).mean()), abs=1e-4)
    assert not list((tmp_path / "cwd").iterdir())  # nothing written outside the run directory


def test_segment_without_students_scores_the_teacher_alone(espnet: Path, tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir

    from semvpr.segment import run, summary

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(
            config_name="segment",
            overrides=[
                f"seg.root={write_camvid(tmp_path / 'camvid')}",
                "seg.image_size=[32,48]",
                "seg.num_workers=0",
                "num_figure_images=1",
                f"paths.cache_dir={tmp_path / 'cache'}",
                "teacher=espnetv2",
                f"teacher.checkpoint={espnet}",
                f"teacher.inference_size=[{SIZE[0]},{SIZE[1]}]",
                "~backbone@backbones.efficientnet_lite0",
            ],
        )
    results = run(cfg, tmp_path / "run")
    assert not any(k.startswith("student_") for k in results) and "pseudo_labels" not in results
    assert set(results["teacher"]["val"]) >= {"miou", "dynamic_iou"}
    assert not list((tmp_path / "cache").glob("labels-*"))  # nothing distilled, nothing labelled
    assert set(summary(results, tmp_path / "run")) >= {"teacher/miou", "teacher/checkpoint"}
