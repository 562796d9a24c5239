"""U-Net student: shapes, skip choice, backbone identity, and a short fit that clearly beats chance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from semvpr.config.schema import typed
from semvpr.core.errors import SemvprError
from semvpr.models.backbones import VGG16Backbone
from semvpr.models.student import Student, StudentSpec
from semvpr.segmentation import training as student_mod
from semvpr.segmentation.pseudolabels import LabelledImages
from semvpr.segmentation.training import build_student, fit_student
from tests.helpers import REPO

SIZE = (32, 48)


@pytest.fixture(scope="module")
def backbone() -> VGG16Backbone:
    torch.manual_seed(0)
    return VGG16Backbone(weights="none", train_from="conv5")


def tiny_cfg() -> OmegaConf:
    """The shipped student config, shrunk for a seconds-long fit."""
    cfg = OmegaConf.load(REPO / "conf/student/unet.yaml")
    cfg.static_classes = ["road", "building"]
    cfg.update(width=16, epochs=20, batch_size=8, num_workers=0, lr=1e-2)
    return cfg


def test_shapes_and_skip_choice(backbone: VGG16Backbone) -> None:
    student = Student(backbone.frozen_channels, backbone.frozen_strides, strides=(4, 8, 16), width=8)
    assert [backbone.frozen_strides[i] for i in student.skip_indices] == [4, 8, 16]
    with torch.no_grad():
        skips = backbone.forward_frozen(torch.rand(2, 3, *SIZE))
        logits = student(skips)
        classes = student.class_prob(skips, out_hw=SIZE)
        prob = student.static_prob(skips, out_hw=SIZE)
    assert logits.shape == (2, 19, SIZE[0] // 4, SIZE[1] // 4)
    torch.testing.assert_close(classes.sum(1), torch.ones(2, *SIZE))
    assert prob.shape == (2, 1, *SIZE) and prob.min() >= 0 and prob.max() <= 1 + 1e-6
    assert Student(backbone.frozen_channels, backbone.frozen_strides, strides=(8,), width=8)(skips).shape[-2:] == (4, 6)


def test_strides_the_backbone_lacks_are_a_user_error(backbone: VGG16Backbone) -> None:
    with pytest.raises(SemvprError, match="frozen feature strides"):
        Student(backbone.frozen_channels, backbone.frozen_strides, strides=(32,))


def test_backbone_identity_tracks_only_the_frozen_prefix(backbone: VGG16Backbone) -> None:
    before = backbone.frozen_identity()
    with torch.no_grad():
        backbone.units[-1][0].weight.add_(1.0)  # conv5: trainable, irrelevant to the student
        assert backbone.frozen_identity() == before
        backbone.units[0][0].weight.add_(1.0)  # conv1: frozen, changes every skip
        assert backbone.frozen_identity() != before
        backbone.units[0][0].weight.sub_(1.0)
        backbone.units[-1][0].weight.sub_(1.0)


def toy_set(root: Path, n: int, seed: int) -> tuple[list[Path], list[np.ndarray]]:
    """Red 'cars' (trainId 13) on a grey 'road' (0), with a strip of ignore; images and trainId maps."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    paths, maps = [], []
    for i in range(n):
        ids = np.zeros(SIZE, np.uint8)
        y, x = rng.integers(0, SIZE[0] // 2), rng.integers(0, SIZE[1] // 2)
        ids[y : y + SIZE[0] // 2, x : x + SIZE[1] // 2] = 13
        img = np.where(ids[..., None] == 13, [200, 30, 30], [110, 110, 110]).astype(np.float32)
        img = np.clip(img + rng.normal(0, 10, img.shape), 0, 255).astype(np.uint8)
        ids[0, :] = 255
        paths.append(root / f"s{seed}_{i:03d}.png")
        Image.fromarray(img).save(paths[-1])
        maps.append(ids)
    return paths, maps


def write_labels(folder: Path, paths: list[Path], maps: list[np.ndarray]) -> Path:
    """Pseudo-label PNGs of ``paths`` in ``folder``, as the pseudo-label stage names them."""
    folder.mkdir()
    for p, ids in zip(paths, maps, strict=True):
        Image.fromarray(ids).save(folder / f"{p.name}.png")
    return folder


def test_short_fit_beats_chance_and_is_cached(
    backbone: VGG16Backbone, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    paths, maps = toy_set(tmp_path / "img", 24, seed=0)
    labels = write_labels(tmp_path / "labels-abc", paths, maps)
    student = build_student(
        typed(StudentSpec, tiny_cfg(), "student"),
        backbone,
        LabelledImages(paths, labels, tmp_path / "img"),
        SIZE,
        tmp_path / "cache",
    )
    assert not student.training

    test_paths, test_maps = toy_set(tmp_path / "test", 8, seed=1)
    from semvpr.data.images import load_image

    images = torch.stack([load_image(p) for p in test_paths])
    with torch.no_grad():
        pred = student.static_prob(backbone.forward_frozen(images), out_hw=SIZE)[:, 0] >= 0.5
    target = torch.from_numpy(np.stack(test_maps))
    valid = target != 255
    static = (target == 0) & valid
    accuracy = (pred == static)[valid].float().mean().item()
    majority = max(static[valid].float().mean().item(), 1 - static[valid].float().mean().item())
    iou = ((pred & static).sum() / (pred & valid | static).sum()).item()
    assert accuracy > majority + 0.1 and accuracy > 0.9, (accuracy, majority)
    assert iou > 0.85, iou

    monkeypatch.setattr(student_mod, "fit_student", lambda *a: pytest.fail("trained twice"))
    again = build_student(
        typed(StudentSpec, tiny_cfg(), "student"),
        backbone,
        LabelledImages(paths, labels, tmp_path / "img"),
        SIZE,
        tmp_path / "cache",
    )
    for a, b in zip(student.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)


def test_multi_class_student_static_sum_is_its_binary_mask(backbone: VGG16Backbone) -> None:
    from semvpr.models.masks import StudentMask, pool_to_grid

    torch.manual_seed(0)
    static = ["road", "sidewalk", "building"]
    student = Student(backbone.frozen_channels, backbone.frozen_strides, width=8, static_names=static).eval()
    images = torch.rand(2, 3, *SIZE)
    with torch.no_grad():
        skips = backbone.forward_frozen(images)
        classes = student.class_prob(skips, out_hw=SIZE)
        mask = StudentMask(student, static)
        binary = mask.grid_mask(images, skips, None, (2, 3), "binary")
        learned = mask.grid_mask(images, skips, None, (2, 3), "learned")
    by_hand = classes[:, 0] + classes[:, 1] + classes[:, 2]  # road, sidewalk, building are trainIds 0..2
    torch.testing.assert_close(student.static_prob(skips, out_hw=SIZE)[:, 0], by_hand)
    assert torch.equal(binary, pool_to_grid(by_hand[:, None], (2, 3)))
    assert learned.shape == (2, 19, 2, 3)
    torch.testing.assert_close(
        learned[:, :3].sum(1, keepdim=True), torch.nn.functional.adaptive_avg_pool2d(by_hand[:, None], (2, 3))
    )


def test_a_flipping_student_reads_each_image_or_its_mirror_with_its_labels(
    backbone: VGG16Backbone, monkeypatch: pytest.MonkeyPatch
) -> None:
    """student.flip: every sample of a batch is an image's own features and labels, or its mirror image's
    features and its labels mirrored; both occur, about half each."""

    n, h, w = 24, SIZE[0] // 4, SIZE[1] // 4
    student = Student(backbone.frozen_channels, backbone.frozen_strides, strides=(4,), width=8)
    channels = backbone.frozen_channels[student.skip_indices[0]]
    # Sample i's features are the constant i + 1, its mirror image's -(i + 1): each read names its source.
    own = torch.arange(1, n + 1, dtype=torch.float32)[:, None, None, None].expand(n, channels, h, w).contiguous()
    targets = torch.from_numpy(np.random.default_rng(0).integers(0, 19, (n, *SIZE), dtype=np.uint8))
    seen: list[tuple[int, bool]] = []
    reads: list[list[int]] = []

    decode = student.decode

    def spy_decode(chosen: list[torch.Tensor]) -> torch.Tensor:
        values = chosen[0][:, 0, 0, 0].tolist()
        reads.append([int(v) for v in values])
        return decode(chosen)

    real_ce = torch.nn.functional.cross_entropy

    def spy_ce(logits: torch.Tensor, target: torch.Tensor, **kw: object) -> torch.Tensor:
        for value, t in zip(reads[-1], target, strict=True):
            i, mirrored = abs(value) - 1, value < 0
            expected = targets[i].long().flip(-1) if mirrored else targets[i].long()
            assert torch.equal(t, expected), (i, mirrored)
            seen.append((i, mirrored))
        return real_ce(logits, target, **kw)

    monkeypatch.setattr(student, "decode", spy_decode)
    monkeypatch.setattr(torch.nn.functional, "cross_entropy", spy_ce)
    spec = StudentSpec(width=8, epochs=4, batch_size=8, bf16=False, flip=True)
    fit_student(student, [own], targets, spec, mirrored=[-own])
    assert sorted({i for i, _ in seen}) == list(range(n)) and len(seen) == 4 * n
    share = sum(m for _, m in seen) / len(seen)
    assert 0.3 < share < 0.7, share
    seen.clear()
    fit_student(student, [own], targets, StudentSpec(width=8, epochs=1, batch_size=8, bf16=False))
    assert len(seen) == n and not any(m for _, m in seen)


def test_a_flipping_student_caches_its_mirror_images_features(backbone: VGG16Backbone, tmp_path: Path) -> None:
    """The mirrored features are the frozen trunk's of the mirrored images (fp32 here), and flip=true is
    another student than flip=false (its own cache entry)."""
    from semvpr.data.images import load_image
    from semvpr.segmentation.training import cache_skips

    paths, maps = toy_set(tmp_path / "img", 6, seed=0)
    indices = [0, 1]
    got = cache_skips(backbone, indices, paths, SIZE, StudentSpec(batch_size=4, num_workers=0, bf16=False), mirror=True)
    images = torch.stack([load_image(p, SIZE) for p in paths]).flip(-1)
    with torch.no_grad():
        expected = backbone.forward_frozen(images)
    for level, i in enumerate(indices):
        # Stored in bf16: one rounding step apart where the batches' fp32 sums differ in the last bits.
        torch.testing.assert_close(got[level].float(), expected[i].float(), rtol=8e-3, atol=4e-3)
    labels = write_labels(tmp_path / "labels-abc", paths, maps)
    cfg = tiny_cfg()
    cfg.update(epochs=1)
    build = lambda c: build_student(  # noqa: E731
        typed(StudentSpec, c, "student"),
        backbone,
        LabelledImages(paths, labels, tmp_path / "img"),
        SIZE,
        tmp_path / "cache",
    )
    build(cfg)
    cfg.update(flip=True)
    build(cfg)
    assert len(list((tmp_path / "cache").glob("student-*"))) == 2


def test_a_student_trained_at_another_thread_count_is_another_cache_entry(
    backbone: VGG16Backbone, tmp_path: Path
) -> None:
    """A multi-threaded CPU training splits its sums by thread, so the thread count it ran at is part of the
    student's key: the same settings at 1 and 2 threads are two entries, each reused at its own count."""
    paths, maps = toy_set(tmp_path / "img", 6, seed=0)
    labels = write_labels(tmp_path / "labels-abc", paths, maps)
    cfg = tiny_cfg()
    cfg.update(epochs=1)
    before = torch.get_num_threads()
    keys = []
    try:
        for threads in (1, 2, 1):
            torch.set_num_threads(threads)
            student = build_student(
                typed(StudentSpec, cfg, "student"),
                backbone,
                LabelledImages(paths, labels, tmp_path / "img"),
                SIZE,
                tmp_path / "cache",
            )
            keys.append(student.artifact.name)
    finally:
        torch.set_num_threads(before)
    assert keys[0] != keys[1] and keys[2] == keys[0]
    assert len(list((tmp_path / "cache").glob("student-*"))) == 2


def test_a_student_folder_that_is_not_one_is_one_line(tmp_path: Path) -> None:
    """A segment run names the students in it, a file says it is one (was: 'not found' for both)."""
    from semvpr.core.errors import SemvprError
    from semvpr.models.student import load_student

    run = tmp_path / "segment_run"
    for name in ("student_vgg16", "student_efficientnet_lite0"):
        (run / name).mkdir(parents=True)
        (run / name / "student.json").write_text("{}")
    line = rf"segment_run is a semvpr.segment run; name a student in it: {run}/student_efficientnet_lite0 or {run}/"
    with pytest.raises(SemvprError, match=line):
        load_student(run, None)
    (tmp_path / "tested.ckpt").write_bytes(b"")
    with pytest.raises(SemvprError, match=r"tested.ckpt is a file; student.checkpoint=DIR names a student saved"):
        load_student(tmp_path / "tested.ckpt", None)


@pytest.mark.parametrize(("precision", "scaled"), [("16-mixed", True), ("bf16-mixed", False), ("32-true", False)])
def test_the_student_scales_its_loss_where_it_trains_in_fp16(
    backbone: VGG16Backbone, monkeypatch: pytest.MonkeyPatch, precision: str, scaled: bool
) -> None:
    """On a GPU without native bf16 (V100, T4) the student's half type is fp16, whose gradients underflow
    without loss scaling (its plain loop had none): there a GradScaler scales the loss, as Lightning's 16-mixed
    does; in bf16 and fp32 none does."""
    import semvpr.segmentation.training as training

    monkeypatch.setattr(training, "device_precision", lambda device_type: precision)
    scales: list[bool] = []
    real = torch.amp.GradScaler.scale

    def spy(self: torch.amp.GradScaler, outputs: torch.Tensor) -> torch.Tensor:
        scales.append(self.is_enabled())
        return real(self, outputs)

    monkeypatch.setattr(torch.amp.GradScaler, "scale", spy)
    n = 8
    student = Student(backbone.frozen_channels, backbone.frozen_strides, strides=(4,), width=8)
    channels = backbone.frozen_channels[student.skip_indices[0]]
    feats = torch.rand(n, channels, SIZE[0] // 4, SIZE[1] // 4)
    targets = torch.from_numpy(np.random.default_rng(0).integers(0, 19, (n, *SIZE), dtype=np.uint8))
    metrics = fit_student(student, [feats], targets, StudentSpec(width=8, epochs=1, batch_size=4, bf16=True))
    assert scales == [scaled, scaled] and np.isfinite(metrics["train/loss"])
