"""Typed settings: the config layer turns a config node into a frozen dataclass here, so the code below it
takes named, typed values instead of a whole config."""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np

from semvpr.core.errors import SemvprError

S = TypeVar("S")


def plain(node: Any) -> Any:
    """``node`` with every mapping a ``dict`` and every sequence other than a list, tuple or text a ``list``
    (a mapping's values read as it gives them: a config node's interpolations resolved)."""
    if isinstance(node, Mapping):
        return {key: plain(value) for key, value in node.items()}
    if isinstance(node, list | tuple):
        return type(node)(plain(value) for value in node)
    if isinstance(node, Sequence) and not isinstance(node, str | bytes):
        return [plain(value) for value in node]
    return node


def set_where(raw: Mapping[str, Any], key: str) -> str:
    """The key a user sets for the value ``key`` reads: ``key`` itself, or the end of the plain interpolations it
    follows (a reader's ``root: ${data.root}`` is set as ``data.root``, which every split reads). ``raw``: the
    whole config as plain mappings, interpolations unresolved (``OmegaConf.to_container(cfg, resolve=False)``)."""
    for _ in range(32):  # a chain; OmegaConf refuses a loop before anything reads it
        value: Any = raw
        for part in key.split("."):
            value = value.get(part) if isinstance(value, Mapping) else None
        follows = re.fullmatch(r"\$\{(\w[\w.]*)\}", value) if isinstance(value, str) else None
        if follows is None:
            break
        key = follows.group(1)
    return key


def unset(raw: Mapping[str, Any], key: str) -> SemvprError:
    """The one line for a value the config leaves unset (``???``) that ``key`` reads, naming the key to set
    (:func:`set_where`)."""
    key = set_where(raw, key)
    return SemvprError(f"{key} is not set; pass it on the command line ({key}=...)")


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
    hints = typing.get_type_hints(cls)
    for name, value in values.items():
        wanted = expected(hints[name], value)
        if wanted is not None:
            raise SemvprError(f"{where}.{name}={value!r}: expected {wanted}")
    check_ranges(cls, values, where)
    return cls(**values)  # type: ignore[call-arg]


def expected(hint: Any, value: Any) -> str | None:
    """What a setting of type ``hint`` takes, where ``value`` is not that (None where it fits, or where the
    type is not one of the plain kinds checked here: bool, int, float, str, sequences (or iterables) of them,
    optional)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        kinds = [a for a in args if a is not type(None)]
        wrong = [expected(k, value) for k in kinds]
        if any(w is None for w in wrong):
            return None
        return " or ".join(w for w in wrong if w) + (" or null" if type(None) in args else "")
    if hint is bool:
        return None if isinstance(value, bool) else "true or false"
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "a whole number"
    if hint is float:
        return None if isinstance(value, int | float) and not isinstance(value, bool) else "a number"
    if hint is str:
        return None if isinstance(value, str) else "a string"
    if origin in (Sequence, Iterable, list, tuple) and len(args) == 1 or (origin is tuple and args[-1:] == (Ellipsis,)):
        item = args[0]
        if not isinstance(value, list | tuple):
            return f"a list of {_kind(item)}"
        return None if all(expected(item, v) is None for v in value) else f"a list of {_kind(item)}"
    return None


def _kind(hint: Any) -> str:
    """A plain type's name in an error line."""
    return {bool: "true / false", int: "whole numbers", float: "numbers", str: "strings"}.get(hint, str(hint))


#: Largest side of an image size any setting or file may give ([H, W] of the data, a teacher's inference
#: size, a saved teacher's or student's training size): a 4096 x 4096 RGB float image is 200 MB before
#: any network sees it.
MAX_IMAGE_SIDE = 4096
#: Largest magnitude a float32 holds: a number read from a file is finite in the dtype it is used in.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def count(value: Any, low: int, high: int) -> bool:
    """Whether ``value`` is a whole number (not a bool) in [low, high]."""
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def image_size(value: Any, where: str) -> list[int]:
    """``value`` as [H, W], each side a whole number from 1 to ``MAX_IMAGE_SIDE``, or one line naming ``where``."""
    if isinstance(value, list | tuple) and len(value) == 2 and all(count(v, 1, MAX_IMAGE_SIDE) for v in value):
        return [int(v) for v in value]
    raise SemvprError(f"{where}={value!r} is not [H, W] (two whole numbers from 1 to {MAX_IMAGE_SIDE})")


def whole_number(value: object, key: str, low: int, high: int | None = None, also: str = "") -> int:
    """``value`` as an int in [low, high], or one line naming ``key`` (``also``: the other values allowed)."""
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= low and (high is None or value <= high)
    if not ok:
        bounds = f"from {low} to {high}" if high is not None else f">= {low}"
        shown = "null" if value is None else repr(value)  # as written on the command line
        must = f"must be {low}" if low == high else f"must be a whole number {bounds}"
        raise SemvprError(f"{key}={shown} {must}{f' ({also})' if also else ''}")
    return int(value)  # type: ignore[arg-type]


def number(value: object, key: str, low: float, *, above: bool = False, high: float | None = None) -> float:
    """``value`` as a finite float >= low (> low with ``above``; <= high if given), or one line naming ``key``."""
    try:
        ok = not isinstance(value, bool) and math.isfinite(float(value))  # type: ignore[arg-type]
        number_ = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        ok, number_ = False, math.nan
    ok = ok and (number_ > low if above else number_ >= low) and (high is None or number_ <= high)
    if not ok:
        bound = f"> {low:g}" if above else f">= {low:g}"
        raise SemvprError(f"{key}={value!r} must be a finite number {bound}" + (f" and <= {high:g}" if high else ""))
    return number_


def float32_number(value: Any) -> bool:
    """Whether ``value`` is a number (not a bool) that stays finite as a float32."""
    return isinstance(value, int | float) and not isinstance(value, bool) and abs(value) <= FLOAT32_MAX


#: The default of a :func:`setting` that its config file must give (OmegaConf's mandatory value).
REQUIRED = "???"


def setting(
    default: Any = REQUIRED,
    *,
    low: float = 0,
    high: float | None = None,
    above: bool = False,
    choices: tuple[str, ...] = (),
    values: tuple[Any, ...] = (),
    also: str = "",
) -> Any:
    """A typed settings field with its range beside it: a whole number or number in [``low``, ``high``]
    (``above``: > ``low``), or one of ``choices``; ``values``: others it takes besides (``-1``: no limit), ``also``
    says what those mean or why the bound is there. A list or tuple field's range is each item's (a tuple of a
    fixed length has that many). Without ``default``, the config file gives the value. Checked by
    :func:`check_ranges` (``config.schema.typed``, :func:`from_mapping`)."""
    meta = {"low": low, "high": high, "above": above, "choices": choices, "values": values, "also": also}
    return dataclasses.field(default=default, metadata=meta)


def check_ranges(schema: type, values: Mapping[str, Any], key: str = "") -> None:
    """Each value of ``values`` (a node's plain values, set at ``key``; "" for the config's top level) against its
    field's :func:`setting`, nested settings dataclasses too: one line naming the key and the value as given."""
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):  # type: ignore[arg-type]
        if f.name not in values:
            continue
        value, where, hint = values[f.name], f"{key}.{f.name}" if key else f.name, hints[f.name]
        args = typing.get_args(hint)
        if type(None) in args:
            if value is None:
                continue
            hint = next(a for a in args if a is not type(None))
        if dataclasses.is_dataclass(hint) and isinstance(value, Mapping):
            check_ranges(hint, value, where)  # type: ignore[arg-type]
        elif f.metadata:
            _check_value(value, hint, f.metadata, where, optional=type(None) in args)


def _check_value(value: Any, hint: Any, meta: Mapping[str, Any], where: str, optional: bool) -> None:
    """One value of a :func:`setting` field of type ``hint``."""
    also = meta["also"] or ("or null" if optional else "")
    origin, items = typing.get_origin(hint), typing.get_args(hint)
    if origin in (list, tuple):
        fixed = origin is tuple and Ellipsis not in items
        if not isinstance(value, list | tuple) or (fixed and len(value) != len(items)) or not value:
            shown = "null" if value is None else repr(value)
            raise SemvprError(f"{where}={shown} must be {also or 'a list'}")
        for i, item in enumerate(value):
            _check_value(item, items[0], {**meta, "also": also}, f"{where}[{i}]", optional=False)
    elif value in meta["values"] and not isinstance(value, bool):
        return
    elif meta["choices"]:
        if value not in meta["choices"]:
            raise SemvprError(f"{where}={value!r} is not one of {list(meta['choices'])}{f' ({also})' if also else ''}")
    elif hint is int:
        whole_number(value, where, int(meta["low"]), None if meta["high"] is None else int(meta["high"]), also)
    elif hint is float:
        number(value, where, meta["low"], above=meta["above"], high=meta["high"])
    elif hint is bool and not isinstance(value, bool):
        raise SemvprError(f"{where}={value!r} must be true or false")
