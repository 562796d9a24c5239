"""The typed schema of the config's settings nodes: one dataclass per node, each setting one field whose type and
range sit beside it (``core.spec.setting``). :func:`typed` reads a node into its dataclass: OmegaConf refuses a key
the schema does not have, a value it leaves unset and a value it cannot convert; the fields' ranges and choices
are checked here, each in one line naming the key as the user sets it. The values themselves live in the yaml
files (``conf/``); a field without a default must be given there.

Adding a setting is one field here and its value in the yaml; the code reads it from the typed node
(``config.plan`` hands the nodes to the builders)."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, ValidationError

from semvpr.core.device import GPU_WORDS
from semvpr.core.errors import SemvprError
from semvpr.core.spec import MAX_IMAGE_SIDE, REQUIRED, check_ranges, setting
from semvpr.data.images import RESIZES
from semvpr.models.masks import WEIGHTINGS
from semvpr.models.released import FORMATS as CKPT_FORMATS
from semvpr.retrieval.controls import APPLIES, CONTROLS

S = TypeVar("S")

#: A model size or count: beyond it a tensor's element count overflows torch's kernels.
SIZE_MAX = 2**31 - 1


def typed(schema: type[S], node: Any, key: str = "", part: bool = False) -> S:
    """The config node ``node`` (set at ``key``: ``model``, ``recipe``; "" for the config's top level) as its
    ``schema`` dataclass, its interpolations resolved; ``part``: only the schema's keys of a node that holds others
    (a reader's, Lightning's). A key the schema lacks, an unset value or one out of its field's type or range is
    one line naming the key and the value."""
    if not isinstance(node, dict | DictConfig):
        raise SemvprError(f"{key}={node!r} must be a mapping of settings")
    names = [f.name for f in dataclasses.fields(schema)]  # type: ignore[arg-type]
    values = {k: _resolved(node, k) for k in node if k in names or not part}
    check_ranges(schema, values, key)
    at = f"{key}." if key else ""
    try:
        return OmegaConf.to_object(OmegaConf.merge(_writable(OmegaConf.structured(schema)), values))  # type: ignore[return-value]
    except ConfigKeyError as err:
        parent, inner = str(err.full_key).rpartition(".")[0], schema
        for name in parent.split(".") if parent else ():  # a nested node's own settings (teacher.train)
            inner = typing.get_type_hints(inner)[name]
        owner = f"{at}{parent}" if parent else f"{key}={values['name']}" if "name" in values else key
        raise SemvprError(
            f"{at}{err.full_key} is not a setting of {owner} (a typo, or one of another {key}?); its settings: "
            f"{', '.join(f.name for f in dataclasses.fields(inner))}"  # type: ignore[arg-type]
        ) from None
    except MissingMandatoryValue as err:
        raise SemvprError(
            f"{at}{err.full_key} is not set; pass it on the command line ({at}{err.full_key}=...)"
        ) from None
    except ValidationError as err:  # a kind the ranges leave to OmegaConf (a number for a text, a list for a number)
        reason = str(err).splitlines()[0]
        if "is not a ListConfig, list or tuple" in reason:
            reason = f"must be a list: {at}{err.full_key}=[...]"
        raise SemvprError(f"{at}{err.full_key}={err.value!r}: {reason}") from None


def _writable(schema: DictConfig) -> DictConfig:
    """A structured config with its nodes writable: OmegaConf makes a frozen dataclass's nodes (nested ones too)
    read-only, so that nothing could be merged into them; the object made from it is frozen all the same."""
    stack: list[Any] = [schema]
    while stack:
        node = stack.pop()
        OmegaConf.set_readonly(node, None)
        keys = node.keys() if OmegaConf.is_dict(node) else range(len(node))
        stack += [child for child in map(node._get_node, keys) if OmegaConf.is_config(child)]  # values unresolved
    return schema


def _resolved(node: Any, key: str) -> Any:
    """``node[key]`` with its interpolations resolved, as plain values (an unset one as OmegaConf's ``???``)."""
    if not isinstance(node, DictConfig):
        return node[key]
    if OmegaConf.is_missing(node, key):
        return REQUIRED
    value = node[key]
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


@dataclass
class ClassWeights:
    """mask.weights=learned: w_c = sigmoid(θ_c), θ_c starting at ±``init_logit``."""

    init_logit: float = setting(low=0)


@dataclass
class Model:
    """The retriever's structure beyond its components (``model``): what a checkpoint records, eval rebuilds."""

    #: pytorch-NetVlad's init asks for 2 neighbours.
    num_clusters: int = setting(
        low=2, high=SIZE_MAX, also="NetVLAD's α is set from each feature's two nearest centroids"
    )
    num_shadows: int = setting(low=1, high=SIZE_MAX)
    init_features: int = setting(low=1, high=SIZE_MAX)
    init_per_image: int = setting(low=1, high=SIZE_MAX)
    eval_batch_size: int = setting(low=1, high=SIZE_MAX)
    pca_dim: int | None = setting(low=1, high=SIZE_MAX, also="or null: no whitening")
    class_weights: ClassWeights = REQUIRED


@dataclass
class Features:
    """How frozen-trunk features are held (``features``; ``retrieval.features``)."""

    storage: str = setting(choices=("auto", "ram", "disk", "stream"))
    ram_gb: float = setting(low=0)
    disk_gb: float = setting(low=0)


@dataclass
class RecipeClassWeights:
    """The learned class weights' learning rate."""

    lr: float = setting(low=0, above=True)


@dataclass
class TripletRecipe:
    """recipe=triplet: NetVLAD's protocol, tuples mined with these radii and counts (``retrieval.mining``)."""

    name: str = REQUIRED
    margin: float = setting(low=0)
    positive_radius: float = setting(low=0, above=True)
    negative_radius: float = setting(low=0, above=True)
    num_negatives: int = setting(low=1)
    negative_candidates: int = setting(low=1)
    queries_per_epoch: int | None = setting(low=1, also="or null: all")
    cache_refresh: int = setting(low=1)
    batch_size: int = setting(low=1)
    class_weights: RecipeClassWeights = REQUIRED
    optimizer: Any = None
    scheduler: Any = None


@dataclass
class GsvRecipe:
    """recipe=gsv: the GSV-Cities recipe, batches of places (``retrieval.places``), the aggregator's published
    optimiser and schedule (``default``: for an aggregator without its own)."""

    name: str = REQUIRED
    places_per_batch: int = setting(low=2)
    images_per_place: int = setting(low=2)
    place_separation: float = setting(low=0)
    traversals: int = setting(low=0)
    max_epochs: int = setting(low=1)
    scheduler_interval: str = setting(choices=("epoch", "step"))
    warmup_steps: int = setting(low=0)
    class_weights: RecipeClassWeights = REQUIRED
    loss: Any = None
    optimizer: Any = None
    scheduler: Any = None
    default: Any = None


#: numpy's (and Lightning's seed_everything) seed range.
SEED_MAX = 2**32 - 1


@dataclass
class BackboneSettings:
    """The backbone group's own settings, beside its class's constructor values (``config.components``)."""

    name: str = REQUIRED
    #: Where the trunk's trainable part starts under experiment=paper (NetVLAD's conv5).
    paper_train_from: Any = None


@dataclass
class AggregatorSettings:
    """The aggregator group's own settings: ``baseline`` labels the report's reference row; ``gsv`` holds the
    authors' schedule under recipe=gsv."""

    name: str = REQUIRED
    baseline: bool = setting(False)
    gsv: Any = None


@dataclass
class MaskSettings:
    """The mask group's own settings: the weighting of the mask (``models.masks``), ``upper_bound`` (the
    report's flag for the oracle) and the mask's control (``retrieval.controls``)."""

    name: str = REQUIRED
    upper_bound: bool = setting(False)
    weights: str = setting(choices=WEIGHTINGS)
    control: str = setting(choices=CONTROLS)
    apply: str = setting(choices=APPLIES)
    control_seed: int = setting(low=0, high=SEED_MAX)


@dataclass
class RunSettings:
    """The top-level settings of a retrieval command (train, eval, localize) that its code reads."""

    seed: int = setting(low=0, high=SEED_MAX)
    #: Test queries whose retrievals and maps the report's figures show.
    num_figure_queries: int = setting(48, low=1)
    #: localize: the database places it lists per query.
    top_k: int = setting(5, low=1)
    #: A sweep's jobs side by side on each GPU (small jobs that leave a GPU idle can share one).
    jobs_per_gpu: int = setting(1, low=1, also="jobs of a sweep side by side on each GPU")
    #: Training steps between two reads of their losses from the device (a non-finite one stops the fit there;
    #: every validation and checkpoint is preceded by one): a read makes the host wait for the device.
    check_loss_every_n_steps: int = setting(50, low=1)


@dataclass
class TrainerSettings:
    """The keys of ``trainer`` that semvpr reads itself (the others are Lightning's Trainer arguments, passed on)."""

    accelerator: str = setting(
        choices=("cpu", *GPU_WORDS), also="trainer=cpu, trainer=gpu: every stage runs on the device it names"
    )
    max_epochs: int = setting(-1, low=1, values=(-1,), also="or -1: no limit")
    devices: int = setting(1, low=1, values=(-1,), also="or -1: every GPU")
    num_nodes: int = setting(1, low=1)
    log_every_n_steps: int | None = setting(None, low=1, also="or null: Lightning's default")
    num_sanity_val_steps: int | None = setting(None, low=-1, also="or null: Lightning's default")
    strategy: str = "auto"
    precision: str = REQUIRED
    #: Lightning's reload (its default is none): without it every epoch trained on epoch 0's batches and mining.
    reload_dataloaders_every_n_epochs: int = setting(
        low=1, high=1, also="every epoch draws its own batches: mining, place sampling"
    )


@dataclass
class OptimizerNode:
    """The keys of ``recipe.optimizer`` (a partial of a torch optimiser) that semvpr reads itself; the class takes
    the others (``_check_optimization`` builds it once on one parameter)."""

    lr: float = setting(low=0, above=True)


@dataclass
class EvalSettings:
    """semvpr.eval's (and localize's and the hub's) top-level settings that its code reads."""

    #: What ``ckpt`` names: a semvpr checkpoint or an author's release layout (``models.released``).
    ckpt_format: str = setting("auto", choices=CKPT_FORMATS)


@dataclass
class DataNode:
    """The keys of ``data`` every place set has (beside its readers'): the image size the models see, loader
    workers, the evaluation radius, how images are resized, the kind of images (``domain``)."""

    name: str = REQUIRED
    image_size: tuple[int, int] = setting(low=1, high=MAX_IMAGE_SIDE, also="[H, W]: two whole numbers")
    num_workers: int = setting(low=0)
    #: Evaluation positives: the database images within this many metres of a query (null: the set's own).
    eval_radius: float | None = setting(None, above=True)
    resize: str = setting("bilinear", choices=RESIZES)
    domain: str | None = None


@dataclass
class SegNode:
    """The keys of ``seg`` (semvpr.segment's segmentation set) beside its readers'."""

    name: str = REQUIRED
    root: str = REQUIRED
    image_size: tuple[int, int] = setting(low=1, high=MAX_IMAGE_SIDE, also="[H, W]: two whole numbers")
    num_workers: int = setting(low=0)


@dataclass
class SegmentSettings:
    """semvpr.segment's top-level settings that its code reads."""

    seed: int = setting(low=0, high=SEED_MAX)
    eval_batch_size: int = setting(low=1, high=SIZE_MAX)
    num_figure_images: int = setting(low=1)
    score_test: bool = setting()


@dataclass
class OtherPlaceSet:
    """A place set an evaluation reads beside the evaluated one: ``init`` (an untrained model's initialisation on
    its training database) and ``pca`` (the PCA-whitening's fitting set)."""

    #: The place set: a conf/data choice with a train split.
    data: str = REQUIRED
    #: Its folder, for the sets that read one.
    root: str | None = None
    #: More of its settings, e.g. ['preset=tiny'].
    overrides: list[str] = dataclasses.field(default_factory=list)


@dataclass
class EvalPca(OtherPlaceSet):
    """semvpr.eval's ``pca``: a PCA-whitening fitted at evaluation on another place set's training database."""

    #: The whitened descriptor's size (null: the model's own descriptors).
    dim: int | None = setting(None, low=1, high=SIZE_MAX, also="or null: no PCA-whitening here")
