"""Typed settings: a config node becomes a frozen dataclass at the config layer, so the code below it
takes named, typed values instead of a whole ``DictConfig``."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf

from semvpr.core.errors import SemvprError

S = TypeVar("S")


def plain(node: Any) -> Any:
    """A config node (or a plain value) as plain Python containers, interpolations resolved."""
    if isinstance(node, DictConfig) or OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)
    return node


def from_mapping(cls: type[S], node: Mapping[str, Any], where: str) -> S:
    """``cls`` from the keys of a config node; a key the dataclass does not have, or a required one the
    node lacks, is one line naming ``where`` (e.g. ``student``)."""
    values = plain(node)
    if not isinstance(values, Mapping):
        raise SemvprError(f"{where} must be a mapping of settings, got {values!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise SemvprError(f"{where}.{unknown[0]} is not a setting of {where} (known: {', '.join(sorted(fields))})")
    missing = [
        name
        for name, f in fields.items()
        if name not in values and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise SemvprError(f"{where}.{missing[0]} is not set")
    return cls(**values)  # type: ignore[call-arg]
