"""What a job decides once from its config, before it builds anything: its settings, typed (:class:`Settings`:
the data, the feature storage, the model, the mask source, the training recipe, the DDP ranks), the device every
stage runs on and the threads of each stage. :func:`settings_of` and :func:`job_plan` make them as the job starts;
the builders (``config/build.py``) take them instead of reading the config again. The nodes a builder
instantiates (a data reader, the backbone, the aggregator, the mask source, the trainer) travel in them as
config nodes: Hydra builds those objects.

A job runs on one device (``core/device.py``): the CPU, or a GPU: a DDP rank's own (its local rank), the one
a sweep job leases (:func:`sweep_gpu`: a GPU per job where several are visible), else the first.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig

from semvpr.config.components import component_class, group_settings, instantiate_node, recipe_of
from semvpr.config.record import record_of
from semvpr.config.schema import DataNode, Features, Model, RunSettings, TripletRecipe, typed
from semvpr.core.device import GPU_WORDS, GpuLease, resolve, visible_gpus
from semvpr.core.threads import JOBS_BESIDE, Threads, standard_start_method, usable_cores
from semvpr.models.masks import MaskSource
from semvpr.models.student import StudentSpec
from semvpr.models.teacher import TeacherSpec
from semvpr.retrieval.controls import MaskControl
from semvpr.retrieval.initialisation import InitSample
from semvpr.retrieval.launch import local_rank
from semvpr.retrieval.losses import TripletLoss
from semvpr.retrieval.mining import Mining
from semvpr.retrieval.places import PlaceBatching
from semvpr.retrieval.retriever import Optimization


@dataclass(frozen=True)
class MaskPlan:
    """A config's mask source, looked up once (:func:`mask_plan`): its class (``source``, None without one), the
    ``mask`` node that builds it, the ``teacher``'s and ``student``'s settings, what a segmenter source is
    made from, and the mask's ``control`` (``mask.control``, ``mask.apply``, ``mask.control_seed``)."""

    source: type[MaskSource] | None
    node: Any
    teacher: TeacherSpec
    student: StudentSpec
    control: MaskControl

    @property
    def needs(self) -> str | None:
        """What the mask source is made from: ``teacher``, ``student``, ``labels`` (the oracle) or None."""
        return self.source.needs if self.source is not None else None


def mask_plan(cfg: DictConfig) -> MaskPlan:
    """The mask source ``cfg`` asks for (its ``mask``, ``teacher`` and ``student`` groups)."""
    return MaskPlan(component_class(cfg, "mask"), cfg.mask, teacher_spec(cfg), student_spec(cfg), mask_control(cfg))


def mask_control(cfg: DictConfig) -> MaskControl:
    """The mask control ``cfg.mask`` sets (checked by ``config.checks``)."""
    mask = group_settings(cfg, "mask")
    return MaskControl(mask.control, mask.apply, mask.control_seed)


@dataclass(frozen=True)
class DataSettings:
    """The place sets of ``data``: the reader node of each split (None where the data has none: evaluation
    only), the image size the models see, loader workers, the evaluation radius, the Cityscapes-format set
    an embedded teacher trains on (``segmentation``: its ``train`` and ``val`` reader nodes, or None), and how
    images are resized to the size (``data.images.RESIZES``: bilinear, or what an author's release file's
    layout sets, ``config.restore.released_retriever``)."""

    name: str
    domain: str | None
    image_size: tuple[int, int]
    num_workers: int
    eval_radius: float | None
    splits: dict[str, Any]
    segmentation: Any
    resize: str = "bilinear"


@dataclass(frozen=True)
class Storage:
    """Where artifacts are cached (``paths.cache_dir``) and how frozen-trunk features are held (``features``:
    ``storage`` auto / ram / disk / stream within ``ram_gb`` and ``disk_gb``)."""

    cache_dir: Path
    storage: str
    ram_gb: float
    disk_gb: float


@dataclass(frozen=True)
class ModelSettings:
    """The retriever's structure: the ``backbone`` and ``aggregator`` nodes (each names its class) and the
    aggregator's class, PCA whitening (``pca_dim``), the describing batch, the aggregator's
    initialisation sample, the mask's ``weighting`` (binary or learned) and ``mask_name``, the static classes
    and the learned class weights' initial logit, and ``record``: what a checkpoint records of the config
    (:func:`~semvpr.config.record.record_of`)."""

    backbone: Any
    aggregator: Any
    aggregator_class: type
    aggregator_name: str
    pca_dim: int | None
    eval_batch_size: int
    init: InitSample
    weighting: str
    mask_name: str
    static_classes: tuple[str, ...]
    init_logit: float
    record: dict[str, Any]


@dataclass(frozen=True)
class Training:
    """How the retriever trains (``recipe``, ``trainer``, ``logger``): the batches its loss trains on (tuples
    mined with ``mining``, or places drawn with ``batching``: the other is None), the optimisation, the Lightning
    trainer's and loggers' nodes, the checkpoint a killed run resumes from (``ckpt_path``) and the test
    queries whose retrievals and maps the report's figures show (``figure_queries``)."""

    mining: Mining | None
    batching: PlaceBatching | None
    optimization: Optimization
    trainer: Any
    loggers: tuple[Any, ...]
    ckpt_path: str | None
    figure_queries: int


@dataclass(frozen=True)
class Settings:
    """A retrieval job's config, typed once (:func:`settings_of`): what the builders read."""

    seed: int
    data: DataSettings
    storage: Storage
    model: ModelSettings
    masks: MaskPlan
    #: DDP processes per node, nodes (:func:`ranks_of`).
    ranks: tuple[int, int]
    #: Whether the aggregator's labelled init or the mask needs the semantic side (teacher, labels, student).
    semantic: bool
    #: The training recipe; None where the job only describes (eval, localize, the hub).
    training: Training | None
    #: The job's ``threads`` setting (auto or a number: semvpr.core.threads) and its trainer's accelerator.
    threads: str | int
    accelerator: str
    #: A sweep's jobs side by side on each GPU (the slots of its lease).
    jobs_per_gpu: int = 1


def data_settings(cfg: DictConfig) -> DataSettings:
    """The ``data`` node of ``cfg``, typed."""
    data = typed(DataNode, cfg.data, "data", part=True)
    return DataSettings(
        name=data.name,
        domain=data.domain,
        image_size=(data.image_size[0], data.image_size[1]),
        num_workers=data.num_workers,
        eval_radius=data.eval_radius,
        splits={split: cfg.data.get(split) for split in ("train", "val", "test")},
        segmentation=cfg.data.get("segmentation"),
        resize=data.resize,
    )


def settings_of(cfg: DictConfig, training: bool = False) -> Settings:
    """The settings of a retrieval job of ``cfg``; ``training`` adds its recipe (:class:`Training`)."""
    model, masks = typed(Model, cfg.model, "model"), mask_plan(cfg)
    features = typed(Features, cfg.features, "features")
    aggregator = component_class(cfg, "aggregator")
    return Settings(
        seed=int(cfg.seed),
        data=data_settings(cfg),
        storage=Storage(Path(str(cfg.paths.cache_dir)), features.storage, features.ram_gb, features.disk_gb),
        model=ModelSettings(
            backbone=cfg.backbone,
            aggregator=cfg.aggregator,
            aggregator_class=aggregator,
            aggregator_name=str(cfg.aggregator.name),
            pca_dim=model.pca_dim,
            eval_batch_size=model.eval_batch_size,
            init=InitSample(model.init_features, model.init_per_image, int(cfg.seed)),
            weighting=str(cfg.mask.weights),
            mask_name=str(cfg.mask.name),
            static_classes=tuple(cfg.teacher.static_classes),
            init_logit=model.class_weights.init_logit,
            record=record_of(cfg),
        ),
        masks=masks,
        ranks=ranks_of(cfg.trainer) if "trainer" in cfg else (1, 1),
        semantic=aggregator.init_sample == "labelled" or masks.needs in ("teacher", "student"),
        training=_training(cfg) if training else None,
        threads=cfg.get("threads", "auto"),
        accelerator=str(cfg.trainer.accelerator) if "trainer" in cfg else "cpu",
        jobs_per_gpu=typed(RunSettings, cfg, part=True).jobs_per_gpu,
    )


def _training(cfg: DictConfig) -> Training:
    """The recipe, trainer and loggers of ``cfg`` (``recipe.batch_size`` is the global batch)."""
    seed, recipe, run = int(cfg.seed), recipe_of(cfg), typed(RunSettings, cfg, part=True)
    node, scheduler = cfg.recipe.get("loss"), cfg.recipe.get("scheduler")
    tuples = isinstance(recipe, TripletRecipe)
    return Training(
        mining=Mining(
            batch_size=recipe.batch_size,
            cache_refresh=recipe.cache_refresh,
            queries_per_epoch=recipe.queries_per_epoch,
            seed=seed,
            positive_radius=recipe.positive_radius,
            negative_radius=recipe.negative_radius,
            num_negatives=recipe.num_negatives,
            negative_candidates=recipe.negative_candidates,
            margin=recipe.margin,
        )
        if tuples
        else None,
        batching=None
        if tuples
        else PlaceBatching(recipe.places_per_batch, recipe.images_per_place, recipe.place_separation, seed),
        optimization=Optimization(
            instantiate(cfg.recipe.optimizer),
            instantiate(scheduler) if scheduler is not None else None,
            recipe.margin if tuples else 0.1,
            recipe.class_weights.lr,
            loss=TripletLoss(recipe.margin) if node is None else instantiate_node(node),
            warmup_steps=0 if tuples else recipe.warmup_steps,
            scheduler_interval="epoch" if tuples else recipe.scheduler_interval,
            check_loss_every_n_steps=run.check_loss_every_n_steps,
        ),
        trainer=cfg.trainer,
        loggers=tuple(cfg.logger.values()),
        ckpt_path=cfg.get("ckpt_path"),
        figure_queries=run.num_figure_queries,
    )


@dataclass(frozen=True)
class JobPlan:
    """One job's decisions: ``device`` (every stage's), ``threads`` (each stage's, adopted for its frozen
    passes) and its ``settings``."""

    device: torch.device
    threads: Threads
    settings: Settings

    @property
    def masks(self) -> MaskPlan:
        """Its mask source."""
        return self.settings.masks

    @property
    def ranks(self) -> tuple[int, int]:
        """DDP processes per node, nodes."""
        return self.settings.ranks

    @property
    def semantic(self) -> bool:
        """Whether it builds the semantic side (teacher, pseudo-labels, student)."""
        return self.settings.semantic


def job_plan(cfg: DictConfig, device: torch.device | None = None, training: bool = True) -> JobPlan:
    """The plan of a job of ``cfg`` on ``device`` (default: :func:`job_device`'s), its threads adopted;
    ``training``: with its recipe (:func:`settings_of`). The training command makes its own from the device
    its sweep leases it."""
    settings = settings_of(cfg, training)
    device = device if device is not None else job_device(settings)
    return JobPlan(device, job_threads(settings, device), settings)


def student_spec(cfg: DictConfig) -> StudentSpec:
    """The student's settings (``cfg.student``)."""
    return typed(StudentSpec, cfg.student, "student")


def teacher_spec(cfg: DictConfig) -> TeacherSpec:
    """The teacher's settings (``cfg.teacher``)."""
    return typed(TeacherSpec, cfg.teacher, "teacher")


def ranks_of(trainer_cfg: DictConfig) -> tuple[int, int]:
    """(processes per node, nodes) of a job: trainer.devices (-1: all GPUs) and trainer.num_nodes
    under a DDP strategy; (1, 1) otherwise."""
    if not str(trainer_cfg.get("strategy", "auto")).startswith("ddp"):
        return 1, 1
    devices = int(trainer_cfg.devices)
    if devices == -1:  # Lightning's "all GPUs"
        devices = torch.cuda.device_count()
    return devices, int(trainer_cfg.get("num_nodes", 1))


def job_device(settings: Settings, leased: int | None = None) -> torch.device:
    """The one device of a training job, from its trainer: the CPU, or a GPU: a DDP rank's own
    (:func:`local_rank`), a sweep job's leased one (``leased``), else the first."""
    if settings.accelerator.lower() not in GPU_WORDS:
        return resolve("cpu")
    if settings.ranks != (1, 1):
        return resolve("cuda", local_rank())
    return resolve("cuda", leased)


@contextmanager
def sweep_gpu(settings: Settings, run_dir: Path) -> Iterator[int | None]:
    """The GPU a one-GPU job of a sweep takes for its life where several are visible (``GpuLease`` in
    :func:`lease_folder`): a slot of ``jobs_per_gpu`` no other job holds, so the jobs launchers run side by side
    share a GPU only as asked; None elsewhere."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    gpus = visible_gpus()
    multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    gpu_job = settings.accelerator.lower() in GPU_WORDS and settings.ranks == (1, 1)
    if not (multirun and gpu_job and len(gpus) > 1):
        yield None
        return
    with GpuLease(lease_folder(settings.storage.cache_dir, run_dir.parent), gpus, settings.jobs_per_gpu) as lease:
        yield lease.index


def lease_folder(cache_dir: Path, sweep_dir: Path) -> Path:
    """Where a sweep job's GPU locks live: ``<paths.cache_dir>/.gpus``, shared by every sweep on the machine
    that uses the cache (two sweeps side by side never take one GPU), or the sweep dir's where the cache
    cannot be written (a read-only cache holding what the runs read)."""
    folder = Path(cache_dir) / ".gpus"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return sweep_dir / ".gpus"
    return folder if os.access(folder, os.W_OK) else sweep_dir / ".gpus"


def launcher_jobs() -> int:
    """How many jobs run side by side with this one: in a sweep, ``hydra.launcher.n_jobs`` under the joblib
    launcher (-1: one per core), else 1; 1 for a job run alone (its config names the sweep launcher all the
    same); for a DDP rank started by its job's rank 0, that job's count (:data:`JOBS_BESIDE`)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    beside = os.environ.get(JOBS_BESIDE, "")
    if beside.isdigit():
        return max(1, int(beside))
    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return 1
    launcher = HydraConfig.get().get("launcher") or {}
    if "joblib" not in str(launcher.get("_target_", "")).lower():
        return 1
    n = launcher.get("n_jobs")
    return usable_cores() if n in (None, -1) else max(1, int(n))


def thread_plan(cfg: DictConfig, gpu: bool | None = None) -> Threads:
    """The threads of this process (``threads``: auto or a number; semvpr.core.threads), given the job's DDP
    ranks on this node and the jobs its launcher runs beside it, and whether its networks run on a GPU
    (``gpu``; by default its trainer's accelerator), adopted as the running job's plan; every command calls
    it (or :func:`job_threads`) as its job starts."""
    ranks = ranks_of(cfg.trainer)[0] if "trainer" in cfg else 1
    if gpu is None:
        gpu = "trainer" in cfg and str(cfg.trainer.accelerator).lower() in GPU_WORDS
    return _adopted_threads(cfg.get("threads", "auto"), ranks, gpu)


def job_threads(settings: Settings, device: torch.device) -> Threads:
    """The threads of a job of ``settings`` on ``device``, adopted (:func:`thread_plan`)."""
    return _adopted_threads(settings.threads, settings.ranks[0], device.type == "cuda")


def _adopted_threads(setting: str | int, ranks: int, gpu: bool) -> Threads:
    """The threads of ``setting`` for ``ranks`` DDP processes on this node, the jobs the launcher runs beside
    this one and its networks on a GPU (``gpu``) or not, adopted as the running job's plan."""
    standard_start_method()  # a job in a joblib worker: data loaders need a standard start method
    return Threads.resolve(setting, ranks, launcher_jobs(), gpu=gpu).adopt()
