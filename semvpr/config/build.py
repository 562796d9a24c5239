"""A run's parts from its config: place sets, backbone, aggregator, mask source, the semantic artifacts
they need (teacher, pseudo-labels, student), feature stores, the retriever and its trainer.

The builders take a job's typed settings (``config.plan``: :class:`~semvpr.config.plan.Settings`, made once
from the config) and turn them into objects: train, eval, localize, segment, the hub and the tests build
through them, so all of them construct exactly the same model. Teacher, pseudo-labels, student and feature
caches come from the artifact cache (built on first use).
"""

from __future__ import annotations

import copy
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import Tensor

from semvpr.config.components import build_component, instantiate_node
from semvpr.config.plan import DataSettings, JobPlan, MaskPlan, ModelSettings, Settings, Training
from semvpr.core.checkpoint import RunCheckpointIO
from semvpr.core.errors import SemvprError
from semvpr.core.logs import say, trainer_kwargs
from semvpr.core.precision import bf16_native, lightning_precision
from semvpr.core.provenance import TrainedOn, data_domain
from semvpr.core.threads import frozen_workers
from semvpr.data.images import Reading
from semvpr.data.places import PlaceSet
from semvpr.models.aggregators.base import Aggregator
from semvpr.models.backbones import Backbone
from semvpr.models.masks import ClassWeights, MaskSource
from semvpr.models.student import Student, load_student, student_architecture
from semvpr.models.teacher import Teacher, embedded_teacher
from semvpr.models.teacher_folder import teacher_architecture
from semvpr.models.whitening import PCAWhitening
from semvpr.retrieval.control_masks import control_features
from semvpr.retrieval.datamodule import EvalDataModule, PlaceDataModule, RetrievalDataModule
from semvpr.retrieval.distributed import Describe
from semvpr.retrieval.features import (
    MaskPass,
    PlaceFeatures,
    StoreSettings,
    choose_storage,
    grid_size,
    place_features,
    skip_bytes,
    trunk_cached,
    trunk_shape,
)
from semvpr.retrieval.initialisation import StaticLabels, initialise_aggregator
from semvpr.retrieval.retriever import Retriever


@dataclass
class Semantic:
    """Semantic artifacts a run needs: teacher, its pseudo-labels of the train images, student, and the seconds
    each took, built or read from the cache (``teacher_s``, ``labels_s``, ``student_s``; ``features_s``: the
    trunk pass that keeps what they read)."""

    teacher: Teacher | None = None
    labels_dir: Path | None = None
    labels_root: Path | None = None
    student: Student | None = None
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class Prepared:
    """What a job builds (or reads from the cache) before any training: the same on every rank."""

    places: dict[str, PlaceSet]
    backbone: Backbone
    semantic: Semantic
    mask_source: MaskSource | None
    features: dict[str, PlaceFeatures]
    storage: str


# ----------------------------------------------------------------------------------- components
def build_places(data: DataSettings, splits: tuple[str, ...] = ("train", "val", "test")) -> dict[str, PlaceSet]:
    """Instantiate the place sets of the requested splits (the data config's readers)."""
    places = {}
    for split in splits:
        if data.splits.get(split) is None:
            raise SemvprError(f"data={data.name} has no {split} split; use it for evaluation only")
        places[split] = instantiate_node(data.splits[split]).with_eval_radius(data.eval_radius)
    return places


def build_backbone(
    node: DictConfig, seed: int, pretrained: bool = True, device: torch.device | str = "cpu"
) -> Backbone:
    """The backbone a ``backbone`` config node names (``_target_``), with the seed's random init or its
    pretrained weights (``pretrained=False`` skips them: a checkpoint carries every weight); channels_last, on
    ``device`` (drawn on the CPU first, so a seed gives the same weights on every device)."""
    torch.manual_seed(seed)
    extra = {} if pretrained else {"weights": "none"}
    return build_component(node, "backbone", **extra).to(device, memory_format=torch.channels_last)


def _aggregator_grid(settings: Settings, backbone: Backbone) -> list[int] | None:
    """The grid an aggregator on a fixed grid (a ``grid`` key) left null is built for: the backbone's at
    data.image_size (None where the aggregator has no grid to fill in)."""
    node = settings.model.aggregator
    if "grid" in node and node.grid is None:
        return list(grid_size(backbone, settings.data.image_size))
    return None


def build_aggregator(settings: Settings, backbone: Backbone) -> Aggregator:
    """The run's aggregator for the backbone's channels, on its :func:`_aggregator_grid` where it takes one."""
    grid = _aggregator_grid(settings, backbone)
    extra = {} if grid is None else {"grid": grid}
    return build_component(settings.model.aggregator, "aggregator", dim=backbone.out_channels, **extra)


def build_mask_source(masks: MaskPlan, backbone: Backbone, semantic: Semantic | None = None) -> MaskSource | None:
    """The mask source of ``masks`` (``config.plan.mask_plan``), given what its class ``needs``: trained (from
    ``semantic``), read from a directory (``teacher.checkpoint`` / ``student.checkpoint``), or untrained for
    weights to be loaded into (``semantic=None``: a checkpoint carries them). A student directory is checked
    against ``backbone``'s frozen trunk, so the backbone must hold its final weights."""
    if masks.source is None:
        return None
    given: dict[str, Any] = {}
    if masks.needs == "teacher":
        given["segmenter"] = semantic.teacher if semantic is not None else teacher_architecture(masks.teacher)
    elif masks.needs == "student":
        spec = masks.student
        if semantic is not None:
            given["segmenter"] = semantic.student
        elif spec.checkpoint:
            given["segmenter"] = load_student(spec.checkpoint, backbone)
        else:
            given["segmenter"] = student_architecture(spec, backbone)
    # On the backbone's device: the source's own buffers (its class weights) as well as its segmenter's.
    source = build_component(masks.node, "mask", **given).to(next(backbone.parameters()).device)
    if semantic is not None or masks.teacher.checkpoint:  # the teacher's weights are final
        link_segmenter(masks, source, backbone)
    return source


def link_segmenter(masks: MaskPlan, mask_source: MaskSource | None, backbone: Backbone) -> None:
    """Let a teacher mask source read ``backbone``'s frozen outputs where its pixel encoder is that trunk
    (``Teacher.link_trunk``) and ``teacher.share_trunk`` allows it; called once the weights of both are final."""
    if mask_source is not None and mask_source.needs == "teacher" and masks.teacher.share_trunk:
        mask_source.segmenter.link_trunk(backbone)


def mask_trained_on(settings: Settings, mask_source: MaskSource | None) -> TrainedOn | None:
    """The data the mask source's segmenter was trained on, as a checkpoint records it: what a segmenter
    directory says, else (a segmenter trained in the run) the run's data; None without a segmenter."""
    segmenter = mask_source.segmenter if mask_source is not None else None
    if segmenter is None:
        return None
    known = getattr(segmenter, "trained_on", None)
    if known is not None:
        return known
    masks = settings.masks
    directory = (masks.teacher if mask_source.needs == "teacher" else masks.student).checkpoint
    if directory:  # a Hub id, or a directory without a record: its name, data unknown
        local = Path(str(directory)).expanduser()
        return TrainedOn(local.name if local.exists() else str(directory), "unknown")
    return TrainedOn(settings.data.name, data_domain(settings.data.domain))


def build_class_weights(model: ModelSettings) -> ClassWeights | None:
    """Learned per-class weights (mask.weights=learned), else None."""
    if model.weighting != "learned":
        return None
    return ClassWeights(list(model.static_classes), model.init_logit)


def build_retriever(settings: Settings, backbone: Backbone, mask_source: MaskSource | None) -> Retriever:
    """The retriever of ``settings`` on this backbone and mask source, its aggregator uninitialised
    (:func:`init_aggregator`) or to be loaded from a checkpoint; with the optimizer where the settings have a
    training recipe. Its record is the config's with the grid a fixed-grid aggregator was built for, and the
    data the mask's segmenter was trained on."""
    model = settings.model
    aggregator = build_aggregator(settings, backbone)
    whitening = PCAWhitening(aggregator.output_dim, model.pca_dim) if model.pca_dim else None
    record = copy.deepcopy(model.record)
    grid = _aggregator_grid(settings, backbone)
    if grid is not None:
        record["config"]["aggregator"]["grid"] = grid
    trained_on = mask_trained_on(settings, mask_source)
    if trained_on is not None:
        record["segmenter"] = trained_on.as_dict()
    retriever = Retriever(
        backbone,
        aggregator,
        mask_source,
        whitening,
        settings.training.optimization if settings.training is not None else None,
        model.eval_batch_size,
        frozen_workers(settings.data.num_workers),  # its image passes: eval's, localize's, the hub's
        record=record,
        class_weights=build_class_weights(model),
    )
    if whitening is not None:  # fixed outside training: DDP need not broadcast its 4096 x D projection each step
        from torch.nn.parallel import DistributedDataParallel

        fixed = [f"whitening.{name}" for name, _ in whitening.named_buffers()]
        DistributedDataParallel._set_params_and_buffers_to_ignore_for_model(retriever, fixed)
    return retriever.to(next(backbone.parameters()).device)


def build_datamodule(settings: Settings, features: dict[str, PlaceFeatures], describe: Describe) -> EvalDataModule:
    """The datamodule the recipe's loss trains on: mined tuples (``describe`` is what mining describes
    with) or place batches."""
    eval_batch, workers = settings.model.eval_batch_size, settings.data.num_workers
    training = _recipe(settings)
    if training.batching is not None:
        return PlaceDataModule(features, training.batching, eval_batch, workers)
    assert training.mining is not None
    return RetrievalDataModule(features, training.mining, describe, eval_batch, workers)


def build_trainer(plan: JobPlan, run_dir: Path, callbacks: list[L.Callback]) -> L.Trainer:
    """The configured Lightning Trainer with the run's loggers and checkpoints, on the plan's device (a
    one-GPU job: that GPU, not the first one). A DDP strategy waits for the ranks as long as rank 0's work
    before ``fit`` may take (:data:`DDP_TIMEOUT`)."""
    training = _recipe(plan.settings)
    if any(str(node.get("_target_", "")).endswith("WandbLogger") for node in training.loggers):
        for variable in ("WANDB_CACHE_DIR", "WANDB_DATA_DIR"):  # wandb's own logs and staging: the cache, not ~/
            os.environ.setdefault(variable, str(Path(plan.settings.storage.cache_dir) / "wandb"))
    loggers = [instantiate(node, save_dir=str(run_dir)) for node in training.loggers]
    trainer = training.trainer
    extra: dict[str, Any] = {}
    if plan.device.type == "cuda" and plan.ranks == (1, 1):
        extra["devices"] = [plan.device.index or 0]
    if str(trainer.get("strategy", "auto")) == "ddp":
        from lightning.pytorch.strategies import DDPStrategy

        extra["strategy"] = DDPStrategy(timeout=DDP_TIMEOUT)
    return instantiate(
        trainer,
        default_root_dir=str(run_dir),
        logger=loggers,
        plugins=[RunCheckpointIO()],  # checkpoints staged in the run dir, not $TMPDIR
        **trainer_kwargs("retriever", callbacks),
        precision=lightning_precision(str(trainer.precision), str(trainer.accelerator)),
        **extra,
    )


def _recipe(settings: Settings) -> Training:
    """The training recipe of ``settings``, which a describing job's settings lack."""
    if settings.training is None:
        raise SemvprError("a retriever's training needs the settings of its recipe: settings_of(cfg, training=True)")
    return settings.training


#: How long a DDP rank waits for the others (process group and collectives): ranks a scheduler started (SLURM,
#: torchrun) wait in the rendezvous while rank 0 alone initialises the aggregator and evaluates the untrained
#: model before ``fit``, which at paper scale takes far more than the default 30 minutes (the ranks semvpr
#: starts itself wait for that in Python: ``retrieval/launch.py``).
DDP_TIMEOUT = timedelta(hours=6)


# ----------------------------------------------------------------------------------- semantic artifacts
def semantic_teacher(plan: JobPlan, backbone: Backbone) -> Teacher:
    """The run's teacher, trained once (cached) or loaded, linked to ``backbone``'s frozen prefix where its
    pixel encoder is that prefix (``Teacher.link_trunk``)."""
    from semvpr.segmentation.training import build_teacher

    spec = plan.masks.teacher
    seg = plan.settings.data.segmentation
    needs_training = spec.checkpoint is None
    seg_train = instantiate_node(seg.train) if needs_training and seg is not None else None
    seg_val = instantiate_node(seg.val) if needs_training and seg is not None else None
    cache_dir, device = plan.settings.storage.cache_dir, next(backbone.parameters()).device
    with plan.threads.stage("teacher"):
        teacher = build_teacher(spec, seg_train, seg_val, cache_dir, device)
    if spec.share_trunk:
        teacher.link_trunk(backbone)
    return teacher


def semantic_levels(
    settings: Settings, backbone: Backbone, teacher: Teacher | None, stand_in: bool = True
) -> tuple[set[int], set[int]]:
    """(the teacher's, the student's) frozen outputs the config's semantic side reads from the trunk pass: the
    teacher's encoder levels where it is linked to the trunk (``teacher``, or where none is given and
    ``stand_in``, the embedded teacher the config trains, whose encoder stays frozen), the student's skips where
    its own pass would run in the trunk pass's precision (bf16 where that is native)."""
    size, masks = settings.data.image_size, settings.masks
    if teacher is None and stand_in:
        wanted = masks.teacher
        if wanted.checkpoint is None and settings.data.segmentation is None:
            return set(), set()  # no teacher to be had: no semantic side on this data
        if wanted.checkpoint is None and wanted.share_trunk and float(wanted.train.backbone_lr_factor) == 0:
            teacher = embedded_teacher(wanted)
            teacher.link_trunk(backbone)
    teacher_levels = set(teacher.trunk_levels or ()) if teacher is not None and teacher.on_trunk(size) else set()
    spec = masks.student
    student_levels: set[int] = set()
    if backbone.image_maps and (spec.bf16 or not bf16_native(next(backbone.parameters()).device.type)):
        student_levels = set(student_architecture(spec, backbone).skip_indices)
    return teacher_levels, student_levels


def skip_plan(
    plan: JobPlan,
    backbone: Backbone,
    places: dict[str, PlaceSet],
    teacher: Teacher | None,
    storage: str,
) -> dict[str, tuple[int, ...]]:
    """Which frozen outputs besides the trunk each split's trunk pass keeps (``skips`` caches), so that the
    semantic side reads them instead of passing the images through the frozen weights again: the teacher's
    encoder levels where it is linked to the trunk (train: its pseudo-labels; every split: its masks), the
    student's skips (train: its training; every split: its masks).

    The jobs of a sweep share these caches. Where the set is small (its trunk held in RAM, and these outputs of
    every split fit ``features.ram_gb`` too), every job's pass keeps all of :func:`semantic_levels` on every
    split, whatever its own mask reads, so that a job with another mask (``filter=unet`` beside
    ``filter=none``) reads them instead of making a pass of its own. None where the trunk is streamed, where
    they would not fit ``features.disk_gb`` and the free disk (then each stage makes its own pass, as it does
    without a linked teacher)."""
    none = {split: () for split in places}
    if storage == "stream":
        return none
    settings = plan.settings
    size, needs, store = settings.data.image_size, plan.masks.needs, settings.storage
    # Only a plan that may keep them for other jobs needs the levels of a teacher this job does not build.
    teacher_levels, student_levels = semantic_levels(settings, backbone, teacher, stand_in=storage == "ram")
    last = len(backbone.frozen_strides) - 1

    def total(levels: dict[str, tuple[int, ...]]) -> int:
        return sum(
            skip_bytes(backbone, size, levels[split], len(p.db_paths) + len(p.q_paths)) for split, p in places.items()
        )

    everything = {split: tuple(sorted((teacher_levels | student_levels) - {last})) for split in places}
    if storage == "ram" and total(everything) <= store.ram_gb * 2**30:
        kept_levels = everything
    else:
        if teacher is None:  # a stand-in's levels are for other jobs only
            teacher_levels = set()
        if needs != "student":
            student_levels = set()
        kept_levels = {}
        for split in places:
            levels = set(teacher_levels) if split == "train" else set()
            levels |= student_levels if split == "train" or needs == "student" else set()
            levels |= teacher_levels if needs == "teacher" else set()
            kept_levels[split] = tuple(sorted(levels - {last}))
    kept = total(kept_levels)
    if kept and choose_storage("auto", kept, store.cache_dir, 0.0, store.disk_gb) == "stream":
        say(
            f"the frozen outputs the semantic side reads ({kept / 2**30:.2f} GiB) exceed the disk "
            "budget: each stage passes the images through the trunk itself"
        )
        return none
    return kept_levels


def trunk_outputs(features: PlaceFeatures) -> Callable[[Sequence[Path]], list[Tensor | None]]:
    """The cached ``forward_frozen`` outputs of a place set's images, by path (database or query)."""
    where = {Path(p): ("q", i) for i, p in enumerate(features.q.paths)}
    where.update({Path(p): ("db", i) for i, p in enumerate(features.db.paths)})
    stores = {"db": features.db, "q": features.q}
    levels = sorted(features.db.levels() & features.q.levels())

    def outputs(paths: Sequence[Path]) -> list[Tensor | None]:
        found = [where[Path(p)] for p in paths]
        out: list[Tensor | None] = [None] * (features.db.trunk_level + 1)
        for side, store in stores.items():
            at = [i for i, (s, _) in enumerate(found) if s == side]
            if not at:
                continue
            part = store.outputs([found[i][1] for i in at], levels)
            for level in levels:
                if out[level] is None:
                    shape, dtype = (len(paths), *part[level].shape[1:]), part[level].dtype
                    out[level] = torch.empty(shape, dtype=dtype, memory_format=torch.channels_last)
                out[level][torch.tensor(at)] = part[level]
        return out

    return outputs


def build_semantic(
    plan: JobPlan,
    train: PlaceSet,
    backbone: Backbone,
    storage: str = "disk",
    skip_levels: Sequence[int] | None = None,
    teacher: Teacher | None = None,
) -> Semantic:
    """Teacher (``teacher`` if given), pseudo-labels and student, as far as the aggregator's init and the mask
    source need them, with the seconds each took (``Semantic.timings``).

    Where the teacher is linked to the trunk and the student reads its skips, both read the train images'
    frozen outputs from the trunk pass's cache (``skip_levels``, by default :func:`skip_plan`'s), so the
    images go through the frozen weights once."""
    from semvpr.segmentation.pseudolabels import LabelledImages, pseudo_labels
    from semvpr.segmentation.training import build_student

    if not plan.semantic:
        return Semantic()
    timings: dict[str, float] = {}
    threads, settings = plan.threads, plan.settings
    workers = threads.workers(settings.data.num_workers)
    size, cache_dir = settings.data.image_size, settings.storage.cache_dir
    tic = time.time()
    if teacher is None:
        teacher = semantic_teacher(plan, backbone)
        timings["teacher_s"] = time.time() - tic
    tic = time.time()
    # The set the semantic side is made from: SynthCity's training split as drawn even where the recipe
    # trains on extra traversals of it, so every recipe gets the same labels and student.
    source = train.for_semantics
    if skip_levels is None or source is not train:
        skip_levels = skip_plan(plan, backbone, {"train": source}, teacher, storage)["train"]
    trunk, held = None, set()
    if skip_levels:
        # Memory-mapped: these are read once, here; the job's stores come later.
        held_as = store_settings(settings, "disk" if storage == "ram" else storage, workers)
        with threads.stage("frozen"):
            frozen = place_features(source, backbone, held_as, skip_levels=skip_levels)
        trunk, held = trunk_outputs(frozen), frozen.db.levels() & frozen.q.levels()
    timings["features_s"] = time.time() - tic
    tic = time.time()
    images = list(source.db_paths) + list(source.q_paths)
    on_trunk = teacher.on_trunk(size) and set(teacher.trunk_levels or ()) <= held
    with threads.stage("frozen"):
        labels_dir = pseudo_labels(
            teacher,
            images,
            Reading(size, plan.masks.teacher.predict_batch_size, workers),
            cache_dir,
            source.root,
            trunk=trunk if on_trunk else None,
        )
    timings["labels_s"], tic = time.time() - tic, time.time()
    semantic = Semantic(teacher, labels_dir, source.root, timings=timings)
    if plan.masks.needs == "student":
        spec = plan.masks.student
        reads = set(student_architecture(spec, backbone).skip_indices) <= held
        with threads.stage("student"):
            labelled = LabelledImages(images, labels_dir, source.root)
            semantic.student = build_student(spec, backbone, labelled, size, cache_dir, trunk=trunk if reads else None)
        timings["student_s"] = time.time() - tic
    return semantic


def store_settings(settings: Settings, storage: str, workers: int | None = None) -> StoreSettings:
    """How the job's place sets are cached and held (``storage``: :func:`feature_storage`'s choice) and its
    frozen pass loads images (``workers``: default ``data.num_workers``)."""
    return StoreSettings(
        settings.data.image_size,
        settings.storage.cache_dir,
        storage,
        settings.model.eval_batch_size,
        settings.data.num_workers if workers is None else workers,
        settings.data.resize,
    )


def feature_storage(settings: Settings, backbone: Backbone, places: dict[str, PlaceSet]) -> str:
    """How the run holds its frozen-trunk features: ram, disk or stream (semvpr.retrieval.features). Under
    DDP every rank on a node holds its own copy in RAM, so ``auto`` gives each a share of
    ``features.ram_gb`` (beyond it the memory-mapped store is shared through the page cache)."""
    size, store = settings.data.image_size, settings.storage
    per_image = 2 * int(np.prod(trunk_shape(backbone, size)))  # bf16
    images = sum(len(p.db_paths) + len(p.q_paths) for p in places.values())
    key, resize = backbone.frozen_key(), settings.data.resize
    cached = all(trunk_cached(p, key, size, store.cache_dir, resize) for p in places.values())
    storage = choose_storage(
        store.storage, per_image * images, store.cache_dir, store.ram_gb / settings.ranks[0], store.disk_gb, cached
    )
    say(f"frozen-trunk features of {images} images ({per_image * images / 2**30:.2f} GiB): {storage}")
    return storage


def prepare(plan: JobPlan, timings: dict[str, float]) -> Prepared:
    """Place sets, backbone, the semantic artifacts and the frozen-trunk features of a training job, all on
    the plan's device, the masks under the plan's control (``retrieval.controls``); the seconds of each stage
    into ``timings`` (data, teacher, labels, student, features: the trunk passes and the masks; semantic =
    teacher + labels + student)."""
    tic = time.time()
    settings, threads = plan.settings, plan.threads
    places = build_places(settings.data)  # generates SynthCity on first use
    timings["data_s"] = time.time() - tic
    backbone = build_backbone(settings.model.backbone, settings.seed, device=plan.device)
    storage = feature_storage(settings, backbone, places)
    semantic, teacher = Semantic(), None
    if plan.semantic:
        tic = time.time()
        teacher = semantic_teacher(plan, backbone)
        timings["teacher_s"] = time.time() - tic
    levels = skip_plan(plan, backbone, places, teacher, storage)
    if teacher is not None:
        semantic = build_semantic(plan, places["train"], backbone, storage, levels["train"], teacher)
        timings.update(semantic.timings)
    mask_source = build_mask_source(plan.masks, backbone, semantic)
    timings["semantic_s"] = sum(timings.get(k, 0.0) for k in ("teacher_s", "labels_s", "student_s"))
    tic = time.time()
    held_as = store_settings(settings, storage, threads.workers(settings.data.num_workers))
    control = plan.masks.control
    masks = None if mask_source is None else MaskPass(mask_source, control.cached_weighting(settings.model.weighting))
    with threads.stage("frozen"):
        features = {
            split: control_features(
                place_features(places[split], backbone, held_as, masks, skip_levels=levels[split]), control
            )
            for split in places
        }
    timings["features_s"] = timings.get("features_s", 0.0) + time.time() - tic
    return Prepared(places, backbone, semantic, mask_source, features, storage)


def init_aggregator(settings: Settings, retriever: Retriever, job: Prepared) -> dict[str, Any]:
    """Initialise the retriever's aggregator from a sample of the job's training features (labelled by
    the teacher's pseudo-labels where it asks for labels); returns what was used."""
    labels = None
    if retriever.aggregator.init_sample == "labelled":
        semantic = job.semantic
        assert semantic.labels_dir is not None and semantic.labels_root is not None
        labels = StaticLabels(
            semantic.labels_dir,
            semantic.labels_root,
            job.places["train"].db_paths,
            list(settings.model.static_classes),
            grid_size(job.backbone, settings.data.image_size),
        )
    train = job.features["train"].db
    return initialise_aggregator(retriever.aggregator, job.backbone, train, settings.model.init, labels)
