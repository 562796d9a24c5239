"""One pass over each image through the frozen trunk: the teacher whose pixel encoder is that trunk reads its
outputs, the trunk pass keeps the skips the semantic side reads, and the shared paths equal the separate ones
(bit for bit, or within the stated float tolerance where the teacher's encoder arithmetic is replaced)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from semvpr.config.build import (
    build_backbone,
    build_mask_source,
    build_places,
    prepare,
    semantic_teacher,
    trunk_outputs,
)
from semvpr.config.plan import data_settings, job_plan, mask_plan, teacher_spec
from semvpr.core.precision import autocast
from semvpr.data.images import load_image
from semvpr.models.masks import StudentMask, TeacherMask, pool_to_grid
from semvpr.models.student import StudentSpec, student_architecture
from semvpr.models.teacher import Teacher, embedded_teacher
from semvpr.retrieval.features import MaskPass, StoreSettings, grid_size, place_features
from semvpr.segmentation.pseudolabels import LabelledImages
from semvpr.segmentation.training import build_student
from tests.helpers import tiny_config

#: Bound on |Δ| of the teacher's semantic scores and class probabilities (values in [0, 1]) between its own
#: encoder (fp32 FrozenBatchNorm activations) and the trunk's outputs (bf16 activations). Measured on the tiny
#: teacher: scores 1.3e-3, probabilities 1.5e-3 under the caches' bf16 autocast.
TOLERANCE = 1e-2
#: Bound on the relative L2 difference of the encoder's feature maps and the trunk's (measured ≤ 1.5 %).
MAP_TOLERANCE = 0.05


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache holding tiny SynthCity and its trained embedded teacher (trained once for the module)."""
    cache = tmp_path_factory.mktemp("shared")
    cfg = tiny_config(cache, "filter=mask2former")
    build_places(data_settings(cfg))
    semantic_teacher(job_plan(cfg), build_backbone(cfg.backbone, 0))
    return cache


def _images(cfg, split: str = "train") -> tuple[list[Path], torch.Tensor]:
    places = build_places(data_settings(cfg))[split]
    paths = [*places.db_paths, *places.q_paths]
    return paths, torch.stack([load_image(p, tuple(cfg.data.image_size)) for p in paths])


def test_the_teacher_links_only_to_the_trunk_its_encoder_is(tmp_path: Path) -> None:
    cfg = tiny_config(tmp_path)
    spec = teacher_spec(cfg)
    trunk = build_backbone(cfg.backbone, 0).eval()
    teacher = embedded_teacher(spec)  # ImageNet encoder, frozen BatchNorm: the default trunk's prefix
    assert teacher.link_trunk(trunk) and teacher.trunk_levels == (1, 2, 3)  # strides 4, 8, 16; 32 its own
    assert teacher.on_trunk((64, 80)) and not teacher.on_trunk((32, 48))  # it sees images at its inference size
    # A trunk whose frozen prefix stops at stride 8 (train_from=stage4): the teacher runs stages 4 and 5 itself.
    short = build_backbone(tiny_config(tmp_path, "backbone.train_from=stage4").backbone, 0).eval()
    assert teacher.link_trunk(short) and teacher.trunk_levels == (1, 2)

    def refused(teacher: Teacher, backbone: torch.nn.Module = trunk) -> bool:
        return not teacher.link_trunk(backbone) and teacher.trunk_levels is None and not teacher.on_trunk((64, 80))

    tuned = embedded_teacher(spec)  # a fine-tuned encoder (teacher.train.backbone_lr_factor > 0)
    with torch.no_grad():
        tuned.model.model.pixel_level_module.encoder._backbone.blocks[2][0].conv_pw.weight[0, 0, 0, 0] += 1e-3
    assert refused(tuned)
    statistics = embedded_teacher(spec)  # BatchNorm statistics re-estimated
    with torch.no_grad():
        statistics.model.model.pixel_level_module.encoder._backbone.bn1.running_var[0] *= 1.01
    assert refused(statistics)
    eps = embedded_teacher(spec)
    eps.model.model.pixel_level_module.encoder._backbone.blocks[0][0].bn1.eps = 1e-5
    assert refused(eps)
    imagenet = Teacher(embedded_teacher(spec).model)  # ImageNet mean/std: another input than the trunk's
    assert refused(imagenet)
    assert refused(embedded_teacher(spec), build_backbone(tiny_config(tmp_path, "backbone=vgg16").backbone, 0))
    swin = teacher_spec(tiny_config(tmp_path, "teacher.model.backbone=swin", "teacher.model.backbone_weights=none"))
    assert refused(embedded_teacher(swin))
    random_trunk = build_backbone(tiny_config(tmp_path, "backbone.weights=none").backbone, 0)
    assert refused(embedded_teacher(spec), random_trunk)


def test_the_teacher_on_the_trunk_equals_its_own_encoder_within_rounding(cache: Path) -> None:
    cfg = tiny_config(cache, "filter=mask2former")
    trunk = build_backbone(cfg.backbone, 0).eval()
    teacher = semantic_teacher(job_plan(cfg), trunk)
    assert teacher.trunk_levels == (1, 2, 3)
    _, images = _images(cfg)
    size = images.shape[-2:]
    with torch.no_grad(), autocast("cpu"):
        outs = trunk.forward_frozen(images.contiguous(memory_format=torch.channels_last))
        own_scores = teacher.semantic_scores(images)
        with autocast("cpu", enabled=teacher.bf16):
            own_maps = teacher.model.model.pixel_level_module.encoder(teacher.pixels(images)).feature_maps
        # The decoder path is Mask2Former's own: the encoder's maps handed over give its scores bit for bit.
        assert torch.equal(teacher.trunk_scores([None, *own_maps[:3]], size), own_scores)
        for own, shared in zip(own_maps[:3], [outs[i] for i in teacher.trunk_levels]):
            assert (own - shared.float()).norm() / own.norm() < MAP_TOLERANCE
        scores = teacher.trunk_scores(outs, size)
        prob, own_prob = teacher.trunk_class_prob(outs, size), teacher.class_prob(images)
        ids, own_ids = teacher.trunk_train_ids(outs, size), teacher.predict_train_ids(images)
    score_gap = (scores - own_scores).abs().max().item()
    assert score_gap < TOLERANCE and (prob - own_prob).abs().max().item() < TOLERANCE
    # Pseudo-labels are the same wherever the teacher's top two classes are more than the rounding apart.
    resized = torch.nn.functional.interpolate(own_scores, size=size, mode="bilinear", align_corners=False)
    top = resized.topk(2, dim=1).values
    clear = (top[:, 0] - top[:, 1]) > 2 * score_gap
    assert torch.equal(ids[clear], own_ids[clear])
    # Binary grid masks are the same wherever the pooled static probability is more than the rounding from 0.5.
    source = TeacherMask(teacher, list(cfg.teacher.static_classes))
    grid = grid_size(trunk, size)
    own_static = torch.nn.functional.adaptive_avg_pool2d(source.static_prob(own_prob), grid)
    static = torch.nn.functional.adaptive_avg_pool2d(source.static_prob(prob), grid)
    gap = (static - own_static).abs().max().item()
    assert gap < TOLERANCE
    clear = (own_static - 0.5).abs() > gap
    assert torch.equal(pool_to_grid(static, grid)[clear], pool_to_grid(own_static, grid)[clear])


def _stores(cfg, cache: Path, places, trunk, source=None, levels=()):
    settings = StoreSettings(tuple(cfg.data.image_size), cache, "ram", 16, 0)
    return place_features(places, trunk, settings, None if source is None else MaskPass(source), skip_levels=levels)


def test_one_trunk_pass_gives_the_trunk_the_skips_and_the_masks_of_separate_passes(cache: Path, tmp_path: Path) -> None:
    cfg = tiny_config(cache, "filter=mask2former")
    trunk = build_backbone(cfg.backbone, 0).eval()
    places = build_places(data_settings(cfg))["train"]
    kept = _stores(cfg, tmp_path / "one", places, trunk, levels=(1, 2))  # one pass: trunk and skips
    plain = _stores(cfg, tmp_path / "two", places, trunk)  # the trunk alone, as without a semantic side
    assert kept.db.levels() == {1, 2, 3} and plain.db.levels() == {3}
    for side in ("db", "q"):
        a, b = getattr(kept, side), getattr(plain, side)
        assert torch.equal(a.trunk.view(torch.uint16), b.trunk.view(torch.uint16))
        # The kept skips are forward_frozen's outputs of the same batches, bit for bit.
        images = torch.stack([load_image(p, tuple(cfg.data.image_size)) for p in a.paths])
        with torch.no_grad(), autocast("cpu"):
            ref = [trunk.forward_frozen(c.contiguous(memory_format=torch.channels_last)) for c in images.split(16)]
        for level in (1, 2):
            expected = torch.cat([r[level] for r in ref]).to(torch.bfloat16)
            assert torch.equal(a.skips[level].view(torch.uint16), expected.view(torch.uint16))
    # Masks computed from the cached outputs equal those of the one pass that runs the trunk for them.
    torch.manual_seed(0)
    student = StudentMask(student_architecture(StudentSpec(width=8), trunk).eval())
    teacher = TeacherMask(semantic_teacher(job_plan(cfg), trunk), list(cfg.teacher.static_classes))
    for source, levels in ((student, (1, 2)), (teacher, (1, 2))):
        assert source.trunk_levels((64, 80)) and not source.reads_pixels((64, 80))
        cached = _stores(cfg, tmp_path / "one", places, trunk, source, levels)
        live = _stores(cfg, tmp_path / "two", places, trunk, source, ())
        for side in ("db", "q"):
            assert torch.equal(getattr(cached, side).mask, getattr(live, side).mask)


def test_the_student_reads_its_skips_from_the_trunk_cache_bit_for_bit(cache: Path, tmp_path: Path) -> None:
    cfg = tiny_config(cache, "filter=unet")
    trunk = build_backbone(cfg.backbone, 0).eval()
    places = build_places(data_settings(cfg))["train"]
    paths = [*places.db_paths, *places.q_paths]
    labels = tmp_path / "labels-x"
    rng = np.random.default_rng(0)
    for p in paths:
        out = labels / p.relative_to(places.root).parent / f"{p.name}.png"
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.choice([0, 2, 8, 10, 13], (64, 80)).astype(np.uint8)).save(out)
    spec = StudentSpec(width=8, epochs=2, batch_size=8, num_workers=0, max_images=30, bf16=True)
    frozen = _stores(cfg, tmp_path / "c1", places, trunk, levels=(1, 2))
    labelled = LabelledImages(paths, labels, places.root)
    shared = build_student(spec, trunk, labelled, (64, 80), tmp_path / "c1", trunk_outputs(frozen))
    own = build_student(spec, trunk, labelled, (64, 80), tmp_path / "c2")
    for name, value in own.state_dict().items():
        assert torch.equal(shared.state_dict()[name], value), name


def _label_key(cache: Path) -> dict:
    (labels,) = cache.glob("labels-*")
    return json.loads((labels / "key.json").read_text())


@pytest.mark.parametrize(
    "overrides",
    [
        ["teacher.share_trunk=false"],
        ["teacher.train.backbone_lr_factor=0.1"],  # the encoder fine-tuned: it is not the trunk any more
        ["backbone=vgg16", "backbone.weights=none"],  # another trunk
    ],
)
def test_a_teacher_that_is_not_the_trunk_runs_its_own_encoder(
    cache: Path, tmp_path: Path, overrides: list[str]
) -> None:
    own = tmp_path / "cache"
    own.mkdir()
    for artifact in cache.glob("synthcity-*"):
        (own / artifact.name).symlink_to(artifact)
    for artifact in cache.glob("teacher-*"):
        (own / artifact.name).symlink_to(artifact)
    # Held on disk, the trunk pass keeps only what this job reads (in RAM it also keeps the student's skips).
    cfg = tiny_config(own, "filter=mask2former", "features.storage=disk", *overrides)
    job = prepare(job_plan(cfg), {})
    teacher = job.semantic.teacher
    assert teacher.trunk_levels is None and not job.mask_source.trunk_levels(tuple(cfg.data.image_size))
    assert job.mask_source.identity(tuple(cfg.data.image_size)).get("encoder") is None
    assert "encoder" not in _label_key(own) and not list(own.glob("skips-*"))
    # Its masks are the teacher's own on the images, batch by batch (the path the committed experiments ran).
    stores = job.features["val"]
    for store in (stores.db, stores.q):
        images = torch.stack([load_image(p, tuple(cfg.data.image_size)) for p in store.paths])
        images = images.contiguous(memory_format=torch.channels_last)  # as the trunk pass hands them over
        assert len(images) <= int(cfg.model.eval_batch_size)
        with torch.no_grad(), autocast("cpu"):
            expected = job.mask_source.grid_mask(images, [], None, grid_size(job.backbone, images.shape[-2:]))
        assert torch.equal(store.mask.float(), expected)


def test_a_linked_run_keys_its_labels_and_masks_apart(cache: Path, tmp_path: Path) -> None:
    own = tmp_path / "cache"
    own.mkdir()
    for artifact in [*cache.glob("synthcity-*"), *cache.glob("teacher-*")]:
        (own / artifact.name).symlink_to(artifact)
    cfg = tiny_config(own, "filter=mask2former")
    job = prepare(job_plan(cfg), {})
    assert job.semantic.teacher.trunk_levels == (1, 2, 3)
    assert _label_key(own)["encoder"] == "trunk"
    assert job.mask_source.identity((64, 80))["encoder"] == "trunk"
    assert len(list(own.glob("skips-*"))) == 6  # strides 4 and 8 of each split, kept by its one trunk pass
    # A mask source rebuilt from the config (as eval rebuilds a checkpoint's) links once its weights are in.
    rebuilt = build_mask_source(mask_plan(cfg), job.backbone)
    assert rebuilt.segmenter.trunk_levels is None
    rebuilt.load_state_dict(copy.deepcopy(job.mask_source.state_dict()))
    from semvpr.config.build import link_segmenter

    link_segmenter(mask_plan(cfg), rebuilt, job.backbone)
    assert rebuilt.segmenter.trunk_levels == (1, 2, 3)
