"""The retriever a command evaluates: a trained checkpoint rebuilt from its record, an author's released file,
or (``ckpt=none``) the
model the config describes with no VPR training. What ``semvpr.eval``, ``semvpr.localize`` and the hub
share.

A checkpoint's model comes from its record (``semvpr.config.record``: validated against the project's
own configs, nothing stored in the file is run) and is assembled by the same builder as a training run.
A command-line choice that would change the model is refused, with two exceptions. The mask source:
``mask=teacher teacher.checkpoint=DIR``, ``mask=student student.checkpoint=DIR`` (directories saved by
``semvpr.segment``, read as data) or ``mask=none`` replaces the checkpoint's own; the backbone, the
aggregator and its weights, and learned class weights stay the checkpoint's (ARCHITECTURE §3.2). And the
mask's control (``mask.control``, ``mask.apply``, ``mask.control_seed``: ``retrieval.controls``): the
invocation's, where it gives one, else the checkpoint's.

An author's released file (pytorch-NetVlad, MixVPR, CosPlace, EigenPlaces, BoQ, SALAD: ``models.released``; told
from a semvpr checkpoint by its keys, or named with ``ckpt_format=``) becomes a record of the same form: the
layout's backbone and aggregator choices and the sizes its weights' shapes give, validated and built the
same way, at the author's image size, with no mask or the invocation's.

``ckpt=none`` is the off-the-shelf baseline: the pretrained trunk and the aggregator's untrained form
(``Aggregator.untrained_form``: plain GeM at p = 3; NetVLAD / SRAL from k-means on the training database
images of the place set ``init.data`` names, never on the evaluated set), with or without a mask from a
directory. Aggregators without an untrained form are refused.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import torch
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf, open_dict

from semvpr.config.build import (
    Prepared,
    build_backbone,
    build_mask_source,
    build_places,
    build_retriever,
    build_semantic,
    feature_storage,
    init_aggregator,
    link_segmenter,
    store_settings,
)
from semvpr.config.checks import check_control_fits, check_model
from semvpr.config.components import component_class, constructor_values, options
from semvpr.config.plan import job_plan, mask_control, settings_of
from semvpr.config.record import check_recorded_paths, model_config
from semvpr.config.schema import OtherPlaceSet, typed
from semvpr.core.checkpoint import (
    FORMAT,
    dtype_fault,
    is_semvpr_checkpoint,
    read_checkpoint,
    read_weights,
    segmenter_of,
)
from semvpr.core.errors import SemvprError
from semvpr.core.io import CONF_DIR
from semvpr.core.logs import say
from semvpr.core.provenance import data_domain
from semvpr.models.released import Release, map_release, read_release
from semvpr.retrieval.features import place_features
from semvpr.retrieval.retriever import Retriever

#: Command-line group choices that would change the model, and the groups each one sets (``mask=`` is
#: the exception: it replaces the mask source, see the module docstring).
MODEL_OVERRIDES = {
    "backbone": ("backbone",),
    "aggregator": ("aggregator",),
    "filter": ("aggregator", "mask"),
}
#: The nodes whose values define a checkpoint's or a release's model (a command-line value there is refused
#: unless it is the model's own or an evaluation honours it).
MODEL_NODES = ("backbone.", "aggregator.", "model.")
#: Model values an evaluation takes from its command line: how the images are described, not what.
EVAL_HONOURS = ("model.eval_batch_size",)
#: The mask sources read from a directory, by what they need: the config group naming the directory.
SEGMENTER_GROUPS = ("teacher", "student")
#: The mask node's control settings (``retrieval.controls``): the invocation's, where it gives them, apply to
#: any model's mask.
CONTROL_KEYS = ("control", "apply", "control_seed")
#: ``ckpt=`` values that mean "no checkpoint: the untrained model of the config".
UNTRAINED = ("none", None)


def is_untrained(ckpt: Any) -> bool:
    """Whether ``ckpt`` asks for the untrained model (``ckpt=none``)."""
    return ckpt in UNTRAINED


def load_retriever(
    cfg: DictConfig,
    explicit: set[str] = frozenset(),
    *,
    new_images: bool = False,
    evaluated: Callable[[], Iterable[Path]] = tuple,
    warn: bool = True,
    ckpt: str | Path | None = None,
    device: torch.device | None = None,
) -> tuple[Retriever, DictConfig]:
    """The retriever ``cfg.ckpt`` names, in eval mode on ``device`` (default: the CPU), and the config it was
    built with.

    ``explicit``: the keys the command line set (a ``mask=`` there replaces the checkpoint's mask source).
    ``new_images``: the caller describes images that come without label maps (localize, the hub), which a
    mask source that reads ground truth cannot, and not as a place set's side, which a mask control needs.
    ``evaluated``: gives the images the retriever will be scored on, which an untrained aggregator's
    initialisation must not see (called only then: a checkpoint is validated before any data is read).
    ``warn``: print one line when the checkpoint's own mask was trained on another kind of images than
    ``cfg.data`` holds. ``ckpt``: the checkpoint file when it is not ``cfg.ckpt`` (the hub passes its path as
    a value, never through Hydra's override syntax, where ``,``, ``=`` and quotes are syntax and ``${...}``
    an interpolation). An untrained model is moved to ``device`` before its initialisation, so its trunk pass,
    k-means and any teacher it trains run there.

    A trained checkpoint's model values are checked as a run's are (``check_model``): a record may hold
    values of the right type that no run could use.
    """
    target = cfg.ckpt if ckpt is None else ckpt
    fmt = str(cfg.get("ckpt_format") or "auto")
    device = torch.device("cpu") if device is None else device
    if is_untrained(target):
        retriever, merged = untrained_retriever(cfg, explicit, evaluated, device)
    else:
        path = Path(str(target))
        contents = read_weights(path, "checkpoint" if fmt in ("auto", "semvpr") else "release file")
        if fmt == "semvpr" or (fmt == "auto" and is_semvpr_checkpoint(contents)):
            retriever, merged = _trained_retriever(cfg, explicit, warn, path, contents)
        else:
            retriever, merged = released_retriever(cfg, explicit, read_release(path, fmt, contents))
    source = retriever.mask_source
    if new_images and source is not None and not source.describes_new_images:
        raise SemvprError(
            f"mask={merged.mask.name} needs ground-truth label maps for every image; it cannot describe new images"
        )
    merged = invocation_control(cfg, explicit, merged)
    check_control_fits(merged.mask, training=False)
    if new_images and mask_control(merged).active:
        raise SemvprError(
            f"mask.control={merged.mask.control} mask.apply={merged.mask.apply} is a control of an evaluation of "
            "a place set; new images are described with the mask source's own mask: add mask.control=none "
            "mask.apply=both"
        )
    return retriever.eval(), merged


def invocation_control(cfg: DictConfig, explicit: set[str], merged: DictConfig) -> DictConfig:
    """``merged`` with the mask control settings the command line gave (``mask.control``, ``mask.apply``,
    ``mask.control_seed``) in place of the checkpoint's; a ``mask=`` that replaced the mask source brought the
    invocation's already."""
    given = [key for key in CONTROL_KEYS if f"mask.{key}" in explicit]
    if not given:
        return merged
    out = merged.copy()
    for key in given:
        out.mask[key] = cfg.mask[key]
    return out


def _trained_retriever(
    cfg: DictConfig, explicit: set[str], warn: bool, path: Path, contents: Any
) -> tuple[Retriever, DictConfig]:
    where = f"checkpoint {path}"
    state, record = read_checkpoint(path, contents)
    merged = model_config(record, cfg, where=where, check_paths=False)
    check_model(merged, where=where)
    trained = _refuse_model_overrides(cfg, explicit, merged, where)
    replaced = replace_mask(cfg, explicit, merged, where)
    if replaced is None:
        check_recorded_paths(record, cfg, where)
    else:
        merged = replaced
        # The checkpoint's own segmenter weights are not loaded; without a mask, neither are class weights.
        dropped = ("mask_source.",) if merged.mask._target_ is not None else ("mask_source.", "class_weights.")
        state = {k: v for k, v in state.items() if not k.startswith(dropped)}
    settings = settings_of(merged)
    masks = settings.masks
    backbone = build_backbone(merged.backbone, settings.seed, pretrained=False)
    retriever = build_retriever(settings, backbone, build_mask_source(masks, backbone) if replaced is None else None)
    misfit = weights_misfit(state, retriever.state_dict())
    if misfit is not None:
        raise SemvprError(f"{where} does not fit {trained}: {misfit}")
    retriever.load_state_dict(state, strict=True)
    if replaced is not None:
        # Built after the checkpoint's weights are in: a student directory is checked against the trunk.
        retriever.mask_source = build_mask_source(masks, backbone)
    else:
        link_segmenter(masks, retriever.mask_source, backbone)  # now that the teacher's weights are the checkpoint's
        if warn:
            warn_foreign_mask(record, merged, where)
    return retriever, merged


def weights_misfit(state: dict[str, Any], expected: dict[str, Any]) -> str | None:
    """How a checkpoint's weights fail the model its record builds (``expected``: that model's state dict), as
    a phrase naming the first key and how many more there are; None when every weight has its place, shape and a
    dtype it can be used in (``core.checkpoint.dtype_fault``)."""
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    reshaped = [k for k in state if k in expected and tuple(state[k].shape) != tuple(expected[k].shape)]
    retyped = {k: why for k in state if k in expected and (why := dtype_fault(state[k], expected[k])) is not None}
    faults = [
        *(f"no weight {k!r}, which the model needs" for k in missing),
        *(f"key {k!r} is not part of the model" for k in extra),
        *(f"{k!r} has shape {tuple(state[k].shape)}, the model needs {tuple(expected[k].shape)}" for k in reshaped),
        *(f"{k!r} {why}" for k, why in retyped.items()),
    ]
    if not faults:
        return None
    return faults[0] + (f" (and {len(faults) - 1} more)" if len(faults) > 1 else "")


def _refuse_model_overrides(cfg: DictConfig, explicit: set[str], merged: DictConfig, where: str) -> str:
    """Refuse (one line) a command-line choice or value that would change the model ``where`` defines (a value
    of the backbone, aggregator or model nodes other than the model's own, e.g. ``model.pca_dim=64``: the
    checkpoint's model would be evaluated without it), and apply those an evaluation honours
    (:data:`EVAL_HONOURS`); returns the model's choices as a phrase."""
    trained = f"backbone={merged.backbone.name} aggregator={merged.aggregator.name} mask={merged.mask.name}"
    for override in sorted(explicit & set(MODEL_OVERRIDES)):
        if any(cfg[group].name != merged[group].name for group in MODEL_OVERRIDES[override]):
            raise SemvprError(
                f"{where} was trained with {trained}; drop the {override}= override "
                "(the model comes from the checkpoint; only mask= may replace its mask source)"
            )
    for key in sorted(k for k in explicit if k.startswith(MODEL_NODES)):
        given, own = OmegaConf.select(cfg, key, default=None), OmegaConf.select(merged, key, default=None)
        if key in EVAL_HONOURS:
            OmegaConf.update(merged, key, given)
        elif given != own:
            shown = lambda v: "null" if v is None else v  # noqa: E731
            hint = " (a PCA-whitening fitted here: pca.dim=N pca.data=SET)" if key == "model.pca_dim" else ""
            raise SemvprError(
                f"{where} defines {key}={shown(own)}, which an evaluation cannot change ({key}={shown(given)} "
                f"would be ignored); drop the override{hint}, or train a model with it"
            )
    return trained


# ----------------------------------------------------------------------------------- released files
def released_retriever(cfg: DictConfig, explicit: set[str], release: Release) -> tuple[Retriever, DictConfig]:
    """The author's model of a release file (``models.released``) as semvpr's backbone and aggregator, with
    no mask or the invocation's (``mask=teacher|student ...``), at the author's image size unless the
    command line sets ``data.image_size``, the images resized as the author's transform does
    (``data.resize``). Its config is validated as a checkpoint's record is."""
    where = release.where
    layout, settings = release.layout, release.settings()
    record = {
        "format": FORMAT,
        "choices": {
            "backbone": layout.backbone,
            "aggregator": layout.aggregator,
            "mask": "none",
            "teacher": str(cfg.teacher.name),
            "student": str(cfg.student.name),
        },
        "config": {
            "backbone": {**settings["backbone"], "weights": "none", "train_from": None},
            "aggregator": settings["aggregator"],
            "model": {**settings["model"], "pca_dim": None},
        },
        "seed": int(cfg.seed),
    }
    merged = model_config(record, cfg, where=where, check_paths=False)
    check_model(merged, where=where)
    _refuse_model_overrides(cfg, explicit, merged, where)
    with open_dict(merged):
        merged.release = layout.label
        merged.data.resize = layout.resize
        if layout.image_size is not None and "data.image_size" not in explicit:
            merged.data.image_size = list(layout.image_size)
    replaced = replace_mask(cfg, explicit, merged, where)
    merged = merged if replaced is None else replaced
    settings = settings_of(merged)
    backbone = build_backbone(merged.backbone, settings.seed, pretrained=False)
    retriever = build_retriever(settings, backbone, None)
    # A release holds the backbone and the aggregator; no whitening, no mask source, no class weights.
    expected = {k: v for k, v in retriever.state_dict().items() if k.startswith(("backbone.", "aggregator."))}
    retriever.load_state_dict(map_release(release, expected), strict=False)
    # Built once the trunk holds the release's weights: a student directory is checked against that trunk.
    retriever.mask_source = build_mask_source(settings.masks, backbone)
    return retriever, merged


def replace_mask(cfg: DictConfig, explicit: set[str], merged: DictConfig, where: str) -> DictConfig | None:
    """``merged`` with the invocation's mask source in place of the checkpoint's, or None when the
    invocation keeps the checkpoint's: a saved segmenter, the ground truth (``mask=oracle``, no weights; the
    evaluated set's label maps, refused where there are none) or none. The learned class weights stay the
    checkpoint's (``mask.weights``); a checkpoint trained without a mask takes a binary one. The directories
    come from the invocation only."""
    given = {group: cfg[group].get("checkpoint") for group in SEGMENTER_GROUPS}
    if "mask" not in explicit:
        for group, value in given.items():
            if f"{group}.checkpoint" in explicit and value and value != merged[group].get("checkpoint"):
                raise SemvprError(
                    f"{group}.checkpoint={value} is not read unless it replaces the checkpoint's mask source "
                    f"(mask={merged.mask.name}): add mask={group}"
                )
        return None
    cls = component_class(cfg, "mask")
    needs = cls.needs if cls is not None else None
    if cfg.mask.name == merged.mask.name and (
        needs not in given or not given[needs] or given[needs] == merged[needs].get("checkpoint")
    ):
        return None  # the checkpoint's own
    if needs in SEGMENTER_GROUPS and not given[needs]:
        raise SemvprError(
            f"mask={cfg.mask.name} replaces the mask source of {where} only with a saved {needs}: add "
            f"{needs}.checkpoint=DIR ({_saved_as(needs)})"
        )
    out = merged.copy()
    own = merged.mask.weights if merged.mask._target_ is not None else None
    with open_dict(out):
        out.mask = OmegaConf.create(OmegaConf.to_container(cfg.mask, resolve=False))
        if cls is None:
            out.mask.weights = "binary"
        elif own is not None:
            if "mask.weights" in explicit and cfg.mask.weights != own:
                raise SemvprError(
                    f"mask.weights={cfg.mask.weights} differs from {where}'s {own} weighting, which stays the "
                    "checkpoint's; drop the override"
                )
            out.mask.weights = own
        elif cfg.mask.weights != "binary":
            raise SemvprError(
                f"{where} was trained without a mask, so it has no learned class weights: "
                f"mask.weights={cfg.mask.weights} needs a checkpoint trained with them; use mask.weights=binary"
            )
        if needs == "teacher" and cfg.teacher.name != merged.teacher.name:  # another kind of teacher: all its own
            out.teacher = OmegaConf.create(OmegaConf.to_container(cfg.teacher, resolve=False))
        for group in SEGMENTER_GROUPS:
            # No directory recorded in the checkpoint is ever read: only the invocation's.
            out[group].checkpoint = given[group] if group == needs else None
        out.teacher.inference_size = cfg.teacher.get("inference_size")
    return out


def _saved_as(group: str) -> str:
    return "<semvpr.segment run>/teacher" if group == "teacher" else "<semvpr.segment run>/student_<backbone>"


def warn_foreign_mask(record: dict[str, Any], merged: DictConfig, where: str) -> None:
    """One stderr line when the checkpoint's own mask comes from a segmenter trained on another kind of
    images than the evaluated data holds, naming the override that replaces it."""
    trained_on = segmenter_of(record, where)
    cls = component_class(merged, "mask")
    if trained_on is None or cls is None or cls.needs not in SEGMENTER_GROUPS or trained_on.domain == "unknown":
        return
    domain = data_domain(merged.data.get("domain"))
    if trained_on.domain == domain:
        return
    say(
        f"warning: {where} has mask={merged.mask.name} from a segmenter trained on "
        f"{trained_on.describe()}, here applied to {domain} images (data={merged.data.name}); a segmenter "
        f"trained on {domain} images replaces it: mask={cls.needs} {cls.needs}.checkpoint=DIR "
        f"({_saved_as(cls.needs)})"
    )


# ----------------------------------------------------------------------------------- ckpt=none
def untrained_retriever(
    cfg: DictConfig,
    explicit: set[str],
    evaluated: Callable[[], Iterable[Path]] = tuple,
    device: torch.device | None = None,
) -> tuple[Retriever, DictConfig]:
    """The config's model with no VPR training, on ``device`` (default: the CPU): the pretrained trunk, the
    aggregator's untrained form (initialised there on ``init.data``'s training database images where it has a
    sample initialisation) and the mask source from its directory, if any."""
    merged = cfg.copy()
    untrained_aggregator(merged, explicit)
    if merged.model.get("pca_dim"):
        raise SemvprError(
            f"ckpt=none: model.pca_dim={merged.model.pca_dim} is a whitening fitted after VPR training; "
            "use model.pca_dim=null"
        )
    if merged.mask.weights != "binary":
        raise SemvprError(
            f"ckpt=none: mask.weights={merged.mask.weights} has class weights that only VPR training learns; "
            "use mask.weights=binary"
        )
    settings = settings_of(merged)
    masks = settings.masks
    if masks.needs in SEGMENTER_GROUPS and not merged[masks.needs].get("checkpoint"):
        raise SemvprError(
            f"ckpt=none: mask={merged.mask.name} needs a saved {masks.needs}: add {masks.needs}.checkpoint=DIR "
            f"({_saved_as(masks.needs)})"
        )
    backbone = build_backbone(merged.backbone, settings.seed).eval()
    retriever = build_retriever(settings, backbone, build_mask_source(masks, backbone))
    retriever.to(torch.device("cpu") if device is None else device)
    if retriever.aggregator.init_sample != "none":
        used = initialise_untrained(merged, retriever, evaluated)
        say(f"ckpt=none: {merged.aggregator.name} initialised on {used}")
    return retriever, merged


def untrained_aggregator(cfg: DictConfig, explicit: set[str]) -> None:
    """Set ``cfg.aggregator``'s values to the aggregator's untrained form, refusing (one line) an aggregator
    that has none, or a command-line setting the untrained form would change."""
    cls = component_class(cfg, "aggregator")
    if cls.untrained_form is None:
        forms = ", ".join(name for name in options("aggregator") if _untrained_form(name) is not None)
        raise SemvprError(
            f"ckpt=none: aggregator={cfg.aggregator.name} has no untrained form (its layers are random until "
            f"VPR training); evaluate a trained checkpoint, or ckpt=none with one of aggregator={forms}"
        )
    settings = constructor_values(cfg.aggregator, "aggregator")
    untrained = cls.untrained_settings(settings)
    for key, value in untrained.items():
        if settings.get(key) == value:
            continue
        if f"aggregator.{key}" in explicit:
            raise SemvprError(
                f"ckpt=none: aggregator.{key}={settings.get(key)!r} has no untrained form (random "
                f"until VPR training); {cfg.aggregator.name}'s is {cls.untrained_form}: drop the override"
            )
        with open_dict(cfg):
            cfg.aggregator[key] = value


def _untrained_form(choice: str) -> str | None:
    """The untrained form of ``conf/aggregator/<choice>.yaml``'s class (None where it has none)."""
    node = OmegaConf.load(Path(CONF_DIR) / "aggregator" / f"{choice}.yaml")
    try:
        return get_class(str(node.get("_target_"))).untrained_form
    except Exception:  # noqa: BLE001 - a file that names no aggregator has no form to offer
        return None


def init_config(cfg: DictConfig) -> DictConfig:
    """``cfg`` with its data replaced by the place set ``init.data`` names (``init.root`` its folder where it
    reads one, ``init.overrides`` more of its settings), at that set's own image size, and no mask: what an
    untrained aggregator's k-means reads."""
    composed = with_place_set(typed(OtherPlaceSet, cfg.init, "init"), "init")
    out = cfg.copy()
    with open_dict(out):
        out.data = composed.data
        out.mask = composed.mask  # none: the k-means sample is the trunk's features alone
    return out


def with_place_set(chosen: OtherPlaceSet, key: str) -> DictConfig:
    """The training config with the place set a command's ``key`` node names beside the evaluated one
    (``config.schema.OtherPlaceSet``: a conf/data choice, its folder where it reads one, more of its settings)."""
    overrides = [f"data={chosen.data}"]
    if chosen.root is not None:
        overrides.append(f"data.root={chosen.root}")
    overrides += [f"data.{o}" for o in chosen.overrides]
    return _compose("train", overrides, key)


def _compose(config_name: str, overrides: list[str], key: str) -> DictConfig:
    """The project's config ``config_name`` with ``overrides`` (from the command's ``key`` node), inside or outside
    a running Hydra app."""
    from hydra import compose, initialize_config_dir

    try:
        if GlobalHydra.instance().is_initialized():
            return compose(config_name=config_name, overrides=overrides)
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            return compose(config_name=config_name, overrides=overrides)
    except SemvprError:
        raise
    except Exception as err:  # noqa: BLE001 - an unknown data choice or a bad override: one line
        raise SemvprError(
            f"{key}.data / {key}.root / {key}.overrides: {str(err).splitlines()[0] if str(err) else err!r}"
        ) from None


def initialise_untrained(cfg: DictConfig, retriever: Retriever, evaluated: Callable[[], Iterable[Path]]) -> str:
    """Initialise the retriever's aggregator as training would, on ``init.data``'s training database images
    (refused if they include an evaluated image); returns what it used, in words."""
    init_cfg = init_config(cfg)
    if init_cfg.data.get("train") is None:
        raise SemvprError(
            f"init.data={cfg.init.data} has no train split to initialise {cfg.aggregator.name} on; name a place "
            "set with one (synthcity, or folder / pitts30k / msls with init.root=DIR)"
        )
    backbone = retriever.backbone
    plan = job_plan(init_cfg, next(backbone.parameters()).device, training=False)
    settings = plan.settings
    places = build_places(settings.data, ("train",))
    train = places["train"]
    seen = {p.resolve() for p in evaluated()}
    shared = [p for p in train.db_paths if p.resolve() in seen] if seen else []
    if shared:
        raise SemvprError(
            f"init.data={cfg.init.data}: {len(shared)} of its training images are evaluated here (e.g. {shared[0]}); "
            "an untrained aggregator's k-means must not see the evaluated set: name another init.data"
        )
    storage = feature_storage(settings, backbone, places)
    semantic = build_semantic(plan, train, backbone, storage=storage)
    features = place_features(train, backbone, store_settings(settings, storage))
    job = Prepared(places, backbone, semantic, None, {"train": features}, storage)
    used = init_aggregator(settings, retriever, job)
    return f"{train.name} ({len(train.db_paths)} database images at {list(init_cfg.data.image_size)}): {used}"


def explicit_keys() -> set[str]:
    """Config keys this invocation overrode on the command line."""
    return {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}
