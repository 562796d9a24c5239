"""Components are classes named in their yaml by a ``_target_`` on the group's own node, the constructor's values
beside it, as every other class in ``conf/`` is named (a reader, the trainer, an optimiser, a loss): a backbone
(``conf/backbone``), an aggregator (``conf/aggregator``) and a mask source (``conf/mask``, ``_target_: null`` for
none). A group's own settings (:data:`COMPONENTS`: its ``name`` and what the run reads beside the class) sit next
to them and are never passed to the class. Each class declares what it needs (an aggregator's ``init_sample``, a
mask source's ``needs``), so no builder switches on a name; adding one is one class and one yaml file. A recipe's
loss (``recipe.loss``) declares the batches it trains on (``batches``) the same way."""

from __future__ import annotations

import collections.abc
import dataclasses
import inspect
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.utils import get_class, get_object, instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationToMissingValueError, MissingMandatoryValue

from semvpr.config.schema import (
    AggregatorSettings,
    BackboneSettings,
    GsvRecipe,
    MaskSettings,
    TripletRecipe,
    typed,
)
from semvpr.core.errors import SemvprError, allocation_failure, unwrap_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.spec import expected, set_where, unset
from semvpr.models.aggregators.base import Aggregator
from semvpr.models.backbones import Backbone
from semvpr.models.masks import MaskSource
from semvpr.retrieval.losses import Loss, TripletLoss


@dataclass(frozen=True)
class Group:
    """A component group: the class its ``_target_`` must be, the schema of the group's own settings beside the
    constructor's values (read by the run, never passed to the class: ``config.schema``), and whether
    ``_target_: null`` (none) is one of its choices."""

    base: type
    schema: type
    optional: bool = False

    @property
    def settings(self) -> tuple[str, ...]:
        """The names of the group's own settings."""
        return tuple(f.name for f in dataclasses.fields(self.schema))


#: The component groups.
COMPONENTS: dict[str, Group] = {
    "backbone": Group(Backbone, BackboneSettings),
    "aggregator": Group(Aggregator, AggregatorSettings),
    "mask": Group(MaskSource, MaskSettings, optional=True),
}


def group_settings(cfg: DictConfig, group: str) -> Any:
    """The group's own settings of ``cfg.<group>``, typed by its schema (``config.schema.typed``)."""
    node = cfg[group]
    schema = COMPONENTS[group].schema
    return typed(schema, {k: node[k] for k in COMPONENTS[group].settings if k in node}, group)


def options(group: str) -> list[str]:
    """The choices of a config group: the names of ``conf/<group>/*.yaml``, sorted."""
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


def _subclass_named(node: Any, base: type) -> tuple[type | None, Any]:
    """The class a config node's ``_target_`` names if it is a subclass of ``base`` (else None), and the target."""
    target = node.get("_target_") if isinstance(node, DictConfig) else None
    try:
        cls = get_class(str(target))
    except Exception:  # noqa: BLE001 - an unimportable name is the same user error
        cls = None
    return (cls if isinstance(cls, type) and issubclass(cls, base) else None), target


def component_class(cfg: DictConfig, group: str) -> type | None:
    """The class ``cfg.<group>._target_`` names (None for ``_target_: null``: no mask), checked without building
    it (a builder reads what it needs first): see :func:`node_class`."""
    return node_class(cfg[group], group)


def node_class(node: DictConfig, group: str) -> type | None:
    """The class a component node names, checked against its group's base class; every key of the node either
    the group's own setting or a parameter of the class (one line naming the first that is neither), of the kind
    the class's annotation says (:func:`refuse_mistyped`)."""
    name = node.get("name")
    if "_target_" not in node:
        raise SemvprError(f"{group}={name}: its file names no class (_target_)")
    spec = COMPONENTS[group]
    if node._target_ is None:
        if not spec.optional:
            raise SemvprError(f"{group}={name}: {group}._target_=null; a {group} is a class")
        return None
    cls, target = _subclass_named(node, spec.base)
    if cls is None:
        base = spec.base
        raise SemvprError(f"{group}={name}: {group}._target_={target!r} is not a {base.__module__}.{base.__name__}")
    params = inspect.signature(cls).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        unknown = sorted(k for k in node if k != "_target_" and k not in spec.settings and k not in params)
        if unknown:
            raise SemvprError(
                f"{group}.{unknown[0]} is not a setting of {group}={name}: {target} takes "
                f"{', '.join(params) or 'nothing'}; the group's own settings are {', '.join(spec.settings)}"
            )
    refuse_mistyped(node, cls, f"{group}={name}")
    return cls


def refuse_mistyped(node: DictConfig, cls: type, owner: str) -> None:
    """A constructor value of another kind than the class's annotation says (``aggregator.p=abc`` for a float,
    ``recipe.scheduler.step_size=2.5`` for a whole number): one line naming it where it is set and ``owner``
    (``aggregator=gem``, or the class), before any work, not the class's own error once the caches are built or
    a value it takes and misreads. Values that do not resolve yet, nulls (a value the builder fills in, as
    MixVPR's ``grid``, or one it refuses by name: :func:`instantiate_node`) and annotations other than the plain
    kinds (``core.spec.expected``) are left to the build."""
    hints = _init_hints(cls)
    try:
        values = OmegaConf.to_container(node, resolve=True, throw_on_missing=True)
    except Exception:  # noqa: BLE001 - an unset value: instantiate_node reports it
        return
    assert isinstance(values, dict)
    for key, value in values.items():
        wanted = expected(hints[key], value) if key in hints and value is not None else None
        if wanted is not None:  # named where it is set (model.num_clusters for NetVLAD's interpolation of it)
            raw = OmegaConf.to_container(node._get_root(), resolve=False)
            source = set_where(raw, f"{node._get_full_key('')}.{key}".lstrip("."))
            raise SemvprError(f"{source}={value!r}: {owner} expects {wanted}")


def refuse_mistyped_values(node: Any) -> None:
    """:func:`refuse_mistyped` for a node naming any importable class (a recipe's optimiser or scheduler); a
    node naming none, or a class that does not import, is left to ``instantiate``'s own line."""
    cls, target = _subclass_named(node, object)
    if cls is not None:
        refuse_mistyped(node, cls, str(target))


#: Names an annotation may use without its module importing them at run time (torch's ``milestones:
#: Iterable[int]`` under postponed annotations): looked up in ``typing`` and ``collections.abc`` where the
#: constructor's own module has no such name.
_ANNOTATION_NAMES: dict[str, Any] = {
    **{k: getattr(typing, k) for k in typing.__all__},
    **{k: getattr(collections.abc, k) for k in collections.abc.__all__},
}


def _init_hints(cls: type) -> dict[str, Any]:
    """The resolved annotations of a class's constructor ({} where one still names what cannot be found)."""
    try:
        init = cls.__init__
        return typing.get_type_hints(init, globalns={**_ANNOTATION_NAMES, **getattr(init, "__globals__", {})})
    except Exception:  # noqa: BLE001 - an unresolvable annotation: nothing to check against
        return {}


def constructor_values(node: DictConfig, group: str) -> dict[str, Any]:
    """The values of a component node its class is built with: every key but ``_target_`` and the group's own
    settings, resolved."""
    values = OmegaConf.to_container(node, resolve=True)
    assert isinstance(values, dict)
    return {k: v for k, v in values.items() if k != "_target_" and k not in COMPONENTS[group].settings}


def build_component(node: DictConfig, group: str, **given: Any) -> Any:
    """The object a component node names (:func:`node_class`), built with its :func:`constructor_values`
    (``given`` adds or replaces some) through :func:`instantiate_node`."""
    if node_class(node, group) is None:
        raise SemvprError(f"{group}={node.get('name')} names no class to build")
    return instantiate_node(node, _leave_out=COMPONENTS[group].settings, **given)


def instantiate_node(node: Any, _leave_out: tuple[str, ...] = (), **kwargs: Any) -> Any:
    """hydra.utils.instantiate, with a SemvprError from inside the target re-raised unwrapped and a missing
    mandatory value (``???``) or a required argument set to null as one line naming its key; the node's keys in
    ``_leave_out`` are not passed to the target."""
    _refuse_null_arguments(node, kwargs)
    try:
        if _leave_out:
            values = OmegaConf.to_container(node, resolve=True, throw_on_missing=True)
            assert isinstance(values, dict)
            return instantiate(OmegaConf.create({k: v for k, v in values.items() if k not in _leave_out}), **kwargs)
        return instantiate(node, **kwargs)
    except Exception as err:
        user = unwrap_user_error(err)
        if user is not None:
            raise user from None
        if isinstance(err, MissingMandatoryValue | InterpolationToMissingValueError):
            raw = OmegaConf.to_container(node._get_root(), resolve=False) if isinstance(node, DictConfig) else {}
            raise unset(raw, err.full_key) from None
        asked = allocation_failure(err)
        if asked is not None:
            path = node._get_full_key("") if isinstance(node, DictConfig) else ""
            sizes = [f"{path}.{k}={v}" if path else f"{k}={v}" for k, v in node.items() if type(v) is int]
            raise SemvprError(
                f"{node.get('_target_')}: building it {asked}; lower its sizes ({', '.join(sizes)})"
            ) from None
        cause: BaseException | None = err
        while cause is not None and not (isinstance(cause, OSError) and cause.filename is not None):
            cause = cause.__cause__ or cause.__context__
        if cause is not None:
            raise cause from None  # a file system refusal about a named file: the CLIs print it in one line
        raise


def _refuse_null_arguments(node: Any, given: dict[str, Any]) -> None:
    """An argument of the node's target without a default and typed without None, set to null: one line
    naming the setting it comes from (``data.root=null`` for a reader's ``root: ${data.root}``), not the
    target's TypeError on None."""
    if not isinstance(node, DictConfig) or node.get("_target_") is None:
        return
    try:
        params = inspect.signature(get_object(str(node._target_))).parameters
    except Exception:  # noqa: BLE001 - an unimportable target is reported by instantiate itself
        return
    for name, param in params.items():
        if name in given or name not in node or param.default is not inspect.Parameter.empty:
            continue
        kind = str(param.annotation)  # a string under postponed annotations
        if param.annotation is inspect.Parameter.empty or any(word in kind for word in ("None", "Optional", "Any")):
            continue  # null may be what it means
        try:
            if node[name] is not None:
                continue
        except Exception:  # noqa: BLE001 - a missing or unresolvable value is reported by instantiate itself
            continue
        key = f"{node._get_full_key('')}.{name}".lstrip(".")
        source = set_where(OmegaConf.to_container(node._get_root(), resolve=False), key)
        raise SemvprError(f"{source}=null, but {node._target_} needs its {name}: set {source}")


def loss_class(cfg: DictConfig) -> type[Loss]:
    """The class of the recipe's loss (``recipe.loss``; a recipe without one trains with the triplet
    loss), checked without building it: its ``batches`` say which datamodule the run needs."""
    node = cfg.recipe.get("loss")
    if node is None:
        return TripletLoss
    cls, target = _subclass_named(node, Loss)
    if cls is None:
        raise SemvprError(
            f"recipe={cfg.recipe.get('name')}: recipe.loss._target_={target!r} is not a {Loss.__module__}.Loss"
        )
    refuse_mistyped(node, cls, str(target))
    return cls


def recipe_of(cfg: DictConfig) -> TripletRecipe | GsvRecipe:
    """``cfg.recipe`` typed by the schema of the batches its loss trains on (:func:`loss_class`): mined tuples
    (recipe=triplet) or drawn places (recipe=gsv)."""
    schema = GsvRecipe if loss_class(cfg).batches == "places" else TripletRecipe
    return typed(schema, cfg.recipe, "recipe")
