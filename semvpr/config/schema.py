"""The typed schema of the config's settings nodes: one dataclass per node, each setting one field whose type and
range sit beside it (:func:`setting`). :func:`typed` reads a node into its dataclass: OmegaConf refuses a key
the schema does not have, a value it leaves unset and a value it cannot convert; the fields' ranges and choices
are checked here, each in one line naming the key as the user sets it. The values themselves live in the yaml
files (``conf/``); a field without a default must be given there.

Adding a setting is one field here and its value in the yaml; the code reads it from the typed node
(``config.plan`` hands the nodes to the builders)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, ValidationError

from semvpr.core.errors import SemvprError
from semvpr.core.spec import REQUIRED, check_ranges, setting
from semvpr.models.masks import WEIGHTINGS
from semvpr.retrieval.controls import APPLIES, CONTROLS

S = TypeVar("S")

#: A model size or count: beyond it a tensor's element count overflows torch's kernels.
SIZE_MAX = 2**31 - 1


def typed(schema: type[S], node: Any, key: str) -> S:
    """The config node ``node`` (set at ``key``: ``model``, ``recipe``) as its ``schema`` dataclass, its
    interpolations resolved; a key the schema lacks, an unset value or one out of its field's type or range is
    one line naming ``key.<field>`` and the value."""
    values = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
    if not isinstance(values, dict):
        raise SemvprError(f"{key}={values!r} must be a mapping of settings")
    check_ranges(schema, values, key)
    try:
        return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), values))  # type: ignore[return-value]
    except ConfigKeyError as err:
        known = ", ".join(f.name for f in dataclasses.fields(schema))  # type: ignore[arg-type]
        owner = f"{key}={values['name']}" if "name" in values else key
        raise SemvprError(
            f"{key}.{err.key} is not a setting of {owner} (a typo, or one of another {key}?); its settings: {known}"
        ) from None
    except MissingMandatoryValue as err:
        raise SemvprError(f"{key}.{err.full_key} is not set; pass it on the command line") from None
    except ValidationError as err:  # a kind the ranges above leave to OmegaConf (a str for a str field...)
        raise SemvprError(f"{key}.{err.full_key}={err.value!r}: {str(err).splitlines()[0]}") from None


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
