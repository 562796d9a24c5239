"""Components are classes named in their yaml by a ``module`` node: a backbone (``conf/backbone``), an
aggregator (``conf/aggregator``) and a mask source (``conf/mask``, ``module: null`` for none). Each
class declares what it needs (an aggregator's ``init_sample``, a mask source's ``needs``), so no builder
switches on a name; adding one is one class and one yaml file. A recipe's loss (``recipe.loss``) declares
the batches it trains on (``batches``) the same way."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

from hydra.utils import get_class, get_object, instantiate
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from semvpr.core.errors import SemvprError, allocation_failure, unwrap_user_error
from semvpr.core.io import CONF_DIR
from semvpr.core.spec import set_where, unset
from semvpr.models.aggregators.base import Aggregator
from semvpr.models.backbones import Backbone
from semvpr.models.masks import MaskSource
from semvpr.retrieval.losses import Loss, TripletLoss

#: The component groups and the class each group's ``module`` must be.
COMPONENTS: dict[str, type] = {"backbone": Backbone, "aggregator": Aggregator, "mask": MaskSource}


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
    """The class ``cfg.<group>.module`` names (None for ``module: null``), checked against its group's base
    class without building it (a builder reads what it needs first)."""
    node = cfg[group].get("module")
    if node is None:
        return None
    base = COMPONENTS[group]
    cls, target = _subclass_named(node, base)
    if cls is None:
        raise SemvprError(
            f"{group}={cfg[group].get('name')}: {group}.module._target_={target!r} is not a "
            f"{base.__module__}.{base.__name__}"
        )
    return cls


def instantiate_node(node: Any, **kwargs: Any) -> Any:
    """hydra.utils.instantiate, with a SemvprError from inside the target re-raised unwrapped and a missing
    mandatory value (``???``) or a required argument set to null as one line naming its key."""
    _refuse_null_arguments(node, kwargs)
    try:
        return instantiate(node, **kwargs)
    except Exception as err:
        user = unwrap_user_error(err)
        if user is not None:
            raise user from None
        if isinstance(err, MissingMandatoryValue):
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
    return cls
