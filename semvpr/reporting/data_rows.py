"""Committed data files read as rows, and what the docs generate or count from them (docs/trust.md,
"Numbers in the docs"): the tables of ``<!-- table: ... -->`` markers, the values of ``<!-- value: ... -->``
markers and the counts of ``<!-- count: ... -->`` markers, all checked by :mod:`semvpr.reporting.claims`.

A *source* is a committed CSV (one row per line), or a JSON / YAML file with an optional ``#/pointer``
to a part of it: a list of objects gives one row per object, an object of objects one row per member
(its name in the field ``key``); nested objects are flattened to dotted fields
(``recall.none.R@1``); a value read from a JSON / YAML source without conditions reads the whole part
as one row, lists too (``per_seed.0.R@1``). Several sources joined by ``+`` are read one after the other,
each row naming its source in the field ``source``.

A *condition* keeps the rows whose field ``F`` ``F=a|b`` is one of the values, ``F!=a|b`` none of them,
``F~a|b`` contains one of them, ``F!~a|b`` none of them, ``F<x`` / ``F>x`` is a number below / above x.
"""

from __future__ import annotations

import csv
import json
import math
import re
import shlex
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from semvpr.core.errors import SemvprError
from semvpr.core.io import read_yaml, regular_file

Row = dict[str, str]

#: A condition: a field name, an operator, the values (``|``-separated).
_CONDITION = re.compile(r"^(?P<field>[^=!~<>]+?)(?P<op>!=|!~|=|~|<|>)(?P<value>.*)$", re.S)
#: A template field: ``{F}`` (as written), ``{F:SPEC}`` (a number in a format spec), ``{-F:SPEC}`` (its negative),
#: ``{F?TEXT}`` (TEXT where the field is yes / true / 1).
_FIELD = re.compile(r"\{(?P<neg>-)?(?P<name>[^{}:?]+)(?::(?P<spec>[^{}]*)|\?(?P<flag>[^{}]*))?\}")
#: A part of a template left out where one of its fields has no value.
_OPTIONAL = re.compile(r"\[\[(.*?)\]\]", re.S)
#: Counts as prose writes them in words.
_WORDS = dict(
    zip(
        ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten", "eleven", "twelve"),
        range(13),
        strict=True,
    )
)
_TRUE = {"yes", "true", "1", "True"}


def _require(path: Path) -> None:
    """A marker's data file must be a committed regular file."""
    if not regular_file(path, "data file"):
        raise SemvprError(f"{path}: no such data file")


def read_rows(path: Path) -> list[Row]:
    """A committed CSV's rows."""
    _require(path)
    with path.open(encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


def read_document(path: Path) -> object:
    """A committed JSON or YAML file."""
    _require(path)
    if path.suffix == ".json":
        return json.loads(path.read_text(encoding="utf-8"))
    return read_yaml(path, "data file")


def pointed(document: object, pointer: str, path: Path) -> object:
    """The part of a JSON / YAML document a pointer names (``/teacher/class_iou``; list items by index)."""
    node = document
    for key in pointer.strip("/").split("/") if pointer.strip("/") else []:
        if isinstance(node, dict) and key in node:
            node = node[key]
        elif isinstance(node, list) and key.isdigit() and int(key) < len(node):
            node = node[int(key)]
        else:
            raise SemvprError(f"{path}: no {pointer!r} in it (a claim's source pointer)")
    return node


def _text(value: object) -> str:
    """A JSON / YAML scalar as a CSV would hold it (lists space-separated, null empty)."""
    if value is None:
        return ""
    if isinstance(value, list):
        return " ".join(_text(v) for v in value)
    return str(value)


def _flat(node: dict, prefix: str = "") -> Row:
    """An object's fields, nested objects as dotted names."""
    row: Row = {}
    for key, value in node.items():
        if isinstance(value, dict):
            row |= _flat(value, f"{prefix}{key}.")
        else:
            row[f"{prefix}{key}"] = _text(value)
    return row


def _one_source(source: str, root: Path) -> list[Row]:
    """The rows of one source (module docstring)."""
    name, _, pointer = source.partition("#")
    path = root / name
    if path.suffix == ".csv" and not pointer:
        return read_rows(path)
    if path.suffix not in (".json", ".yaml", ".yml"):
        raise SemvprError(f"{source}: a source must be a .csv, or a .json or .yaml file with an optional #/pointer")
    node = pointed(read_document(path), pointer, path)
    if isinstance(node, list):
        return [_flat(item) for item in node if isinstance(item, dict)]
    if isinstance(node, dict):
        return [{"key": str(k), **_flat(v)} for k, v in node.items() if isinstance(v, dict)]
    raise SemvprError(f"{source}: names no list or object of rows")


def _document_row(node: object, prefix: str = "") -> Row:
    """A JSON / YAML part as one row: every scalar under it, named by its dotted path."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else None
    if items is None:
        return {prefix.rstrip("."): _text(node)}
    row: Row = {}
    for key, value in items:
        row |= _document_row(value, f"{prefix}{key}.")
    return row


def source_rows(sources: str, root: Path) -> list[Row]:
    """The rows of ``+``-joined sources, each with its source in ``source`` (module docstring)."""
    return [
        {"source": source, **row} if "source" not in row else row
        for source in sources.split("+")
        for row in _one_source(source, root)
    ]


@dataclass(frozen=True)
class Condition:
    """One condition on a row (module docstring)."""

    field: str
    op: str
    values: tuple[str, ...]

    @classmethod
    def parse(cls, text: str) -> Condition:
        """``F=a|b``, ``F!=a``, ``F~a``, ``F!~a``, ``F<0``, ``F>0``."""
        m = _CONDITION.match(text)
        if m is None:
            raise SemvprError(
                f"{text!r}: expected a condition FIELD=a|b, FIELD!=a, FIELD~a, FIELD!~a, FIELD<x or FIELD>x"
            )
        values = tuple(m["value"].split("|"))
        if m["op"] in "<>" and not _is_number(values[0]):
            raise SemvprError(f"{text!r}: {m['op']} compares with a number")
        return cls(m["field"], m["op"], values)

    def holds(self, row: Row) -> bool:
        """The row meets the condition (a row without the field meets none but ``!=`` and ``!~``)."""
        value = row.get(self.field)
        if value is None:
            return self.op in ("!=", "!~")
        if self.op == "=":
            return value in self.values
        if self.op == "!=":
            return value not in self.values
        if self.op == "~":
            return any(v in value for v in self.values)
        if self.op == "!~":
            return not any(v in value for v in self.values)
        if not _is_number(value):
            return False
        return float(value) < float(self.values[0]) if self.op == "<" else float(value) > float(self.values[0])


def _is_number(text: str) -> bool:
    """The text is a finite number."""
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _check_fields(rows: Sequence[Row], names: Iterable[str], source: str) -> None:
    """Every named field is a column of the source's rows (a misspelt one is an error, not empty cells)."""
    known = {k for row in rows for k in row}
    for name in names:
        if name not in known:
            raise SemvprError(f"{source}: no column {name!r} (columns: {', '.join(sorted(known))})")


def count_rows(args: Sequence[str], root: Path) -> int:
    """How many rows of a source meet every condition: ``SOURCE COND ...`` (a count marker's arguments)."""
    if not args:
        raise SemvprError("expected '<!-- count: SOURCE CONDITION ... -->'")
    rows = source_rows(args[0], root)
    conditions = [Condition.parse(a) for a in args[1:]]
    _check_fields(rows, [c.field for c in conditions], args[0])
    return sum(all(c.holds(row) for c in conditions) for row in rows)


def stated_count(text: str) -> int | None:
    """A count as written: digits or a word up to twelve; None for anything else."""
    text = text.strip().lower()
    if text.isdigit():
        return int(text)
    return _WORDS.get(text)


def _number(value: str, spec: str, negated: bool = False) -> str:
    """A field in a format spec, the minus typographic; ``.1%``: a fraction as a percentage (``87.7 %``);
    ``negated``: the field's negative (a loss written as the size of a negative gain)."""
    if not _is_number(value):
        raise SemvprError(f"expected a number in the data file, got {value!r}")
    number = -float(value) if negated else float(value)
    try:
        text = format(100.0 * number, spec[:-1] + "f") + " %" if spec.endswith("%") else format(number, spec)
    except ValueError:
        raise SemvprError(f"{{:{spec}}} is not a number format (for example {{:.1f}}, {{:+.1f}}, {{:.1%}})") from None
    return text.replace("-", "−")


def fill(template: str, row: Row) -> str | None:
    """A template's text for a row: its fields filled in, each ``[[...]]`` part left out where one of its
    fields has no value in the row (``{F?TEXT}`` needs none); None where a field outside such a part has
    none."""

    def filled(text: str) -> str | None:
        missing = False

        def field(m: re.Match[str]) -> str:
            nonlocal missing
            value = row.get(m["name"], "")
            if m["flag"] is not None:
                return m["flag"] if value in _TRUE else ""
            if value == "":
                missing = True
                return ""
            if m["neg"]:
                return _number(value, m["spec"] or "", negated=True)
            return _number(value, m["spec"]) if m["spec"] else value

        text = _FIELD.sub(field, text)
        return None if missing else text

    return filled(_OPTIONAL.sub(lambda m: filled(m[1]) or "", template))


def template_fields(template: str) -> list[str]:
    """The fields a template names."""
    return [m["name"] for m in _FIELD.finditer(template)]


@dataclass(frozen=True)
class TableSpec:
    """A table marker's arguments: ``SOURCE KEYS [METRICS] [OPTION=VALUE ...]`` (docs/trust.md).

    ``KEYS``: the comma-separated fields that label a row (joined by ' · '); ``METRICS``: comma-separated
    fields, each shown as ``<m>_mean ± <m>_std`` (or ``<m>`` alone) at one decimal. Options:
    ``col=LABEL=TEMPLATE`` a column (:func:`fill`: ``{F:.1f}``, ``{F:.1%}``, ``{-F:.1f}``, ``{F?*}``,
    ``[[...]]``), ``where=CONDITION`` keeps rows, ``pivot=FIELD[,FIELD]`` makes each value of the fields
    (joined by ' · ') a group of columns, ``groups=LABEL|LABEL`` picks and orders those groups (as shown),
    ``rows=LABEL|LABEL`` picks and orders rows by label, ``as=VALUE=LABEL`` shows a key value or a group
    as LABEL, ``head=TEXT`` heads the label column.
    """

    source: str
    keys: tuple[str, ...]
    columns: tuple[tuple[str, str], ...]
    where: tuple[Condition, ...] = ()
    pivot: tuple[str, ...] = ()
    groups: tuple[str, ...] = ()
    rows: tuple[str, ...] = ()
    renames: tuple[str, ...] = ()
    head: str | None = None

    @classmethod
    def parse(cls, args: Sequence[str], metric_fields: Iterable[str] = ()) -> TableSpec:
        """The spec of a marker's arguments (split as a shell splits: quote a value with spaces)."""
        positional = [a for a in args if not re.match(r"^(col|where|pivot|groups|rows|as|head)=", a)]
        if len(positional) not in (2, 3):
            raise SemvprError("expected '<!-- table: SOURCE KEYS [METRICS] [OPTION=VALUE ...] -->'")
        source, keys, *metrics = positional
        known = set(metric_fields)
        columns = [
            (m, f"{{{m}_mean:.1f}}[[ ± {{{m}_std:.1f}}]]" if f"{m}_mean" in known else f"{{{m}:.1f}}")
            for m in (metrics[0].split(",") if metrics else [])
        ]
        where, renames, rows, pivot, groups, head = [], [], (), (), (), None
        for arg in args:
            name, _, value = arg.partition("=")
            if arg in positional:
                continue
            if name == "col":
                label, sep, template = value.partition("=")
                if not sep:
                    raise SemvprError(f"{arg!r}: expected col=LABEL=TEMPLATE")
                columns.append((label, template))
            elif name == "where":
                where.append(Condition.parse(value))
            elif name == "as":
                if "=" not in value:
                    raise SemvprError(f"{arg!r}: expected as=VALUE=LABEL")
                renames.append(value)
            elif name == "rows":
                rows = tuple(value.split("|"))
            elif name == "pivot":
                pivot = tuple(value.split(","))
            elif name == "groups":
                groups = tuple(value.split("|"))
            else:
                head = value
        if not columns:
            raise SemvprError(f"{source}: a table needs METRICS or a col=LABEL=TEMPLATE")
        return cls(
            source, tuple(keys.split(",")), tuple(columns), tuple(where), pivot, groups, rows, tuple(renames), head
        )

    def shown_as(self, values: Iterable[str]) -> dict[str, str]:
        """The ``as=VALUE=LABEL`` options as a map of the key values and groups that ``values`` holds (the
        first ``=`` after which the prefix is one of them ends VALUE: both sides may hold ``=``)."""
        known, shown = set(values), {}
        for option in self.renames:
            cuts = [i for i, char in enumerate(option) if char == "=" and option[:i] in known]
            if not cuts:
                raise SemvprError(f"'as={option}': names no key value or group of {self.source}")
            shown[option[: cuts[0]]] = option[cuts[0] + 1 :]
        return shown

    @classmethod
    def of_marker(cls, args: Sequence[str], root: Path) -> TableSpec:
        """The spec of a marker, its METRICS resolved against the source's columns."""
        if not args:
            raise SemvprError("expected '<!-- table: SOURCE KEYS [METRICS] [OPTION=VALUE ...] -->'")
        return cls.parse(args, {k for row in source_rows(args[0], root) for k in row})


def render_table(spec: TableSpec, root: Path) -> str:
    """The markdown table a spec makes of its source: one row per label (its KEYS' values), in the order
    of the source or of ``rows``; with ``pivot``, one group of columns per value of those fields."""
    rows = source_rows(spec.source, root)
    fields = [*spec.keys, *(c.field for c in spec.where), *spec.pivot]
    _check_fields(rows, [*fields, *(f for _, t in spec.columns for f in template_fields(t))], spec.source)
    kept = [row for row in rows if all(c.holds(row) for c in spec.where)]
    shown = spec.shown_as(
        {row[k] for row in kept for k in spec.keys} | {" · ".join(row[f] for f in spec.pivot) for row in kept}
    )
    by_label: dict[str, dict[str | None, Row]] = {}
    groups: list[str | None] = [] if spec.pivot else [None]
    lines = []
    for row in kept:
        label = " · ".join(shown.get(row[k], row[k]) for k in spec.keys)
        group = shown.get(joined := " · ".join(row[f] for f in spec.pivot), joined) if spec.pivot else None
        if spec.groups and group not in spec.groups:
            continue
        if group not in groups:
            groups.append(group)
        if not spec.pivot:
            lines.append((label, {None: row}))
            continue
        cells = by_label.setdefault(label, {})
        if group in cells:
            raise SemvprError(f"{spec.source}: two rows for {label!r} in {','.join(spec.pivot)} {group!r}")
        cells[group] = row
    if spec.pivot:
        lines = list(by_label.items())
    if spec.groups:
        absent = [g for g in spec.groups if g not in groups]
        if absent:
            raise SemvprError(f"{spec.source}: no group {absent[0]!r} (groups: {' | '.join(map(str, groups))})")
        groups = list(spec.groups)
    if spec.rows:
        labelled = dict(lines)
        absent = [r for r in spec.rows if r not in labelled]
        if absent:
            raise SemvprError(f"{spec.source}: no row {absent[0]!r} (rows: {' | '.join(labelled)})")
        lines = [(r, labelled[r]) for r in spec.rows]
    one = len(spec.columns) == 1
    heads = [
        (group if one else f"{group} {label}") if group is not None else label
        for group in groups
        for label, _ in spec.columns
    ]
    out = [f"| {spec.head or ' · '.join(spec.keys)} | " + " | ".join(heads) + " |", "|---|" + "---:|" * len(heads)]
    for label, cells in lines:
        values = [
            (fill(template, cells[group]) if group in cells else None) or "–"
            for group in groups
            for _, template in spec.columns
        ]
        out.append(f"| {label} | " + " | ".join(values) + " |")
    return "\n".join(out)


def value_text(args: Sequence[str], root: Path) -> str:
    """A value marker's text: ``SOURCE [CONDITION ...] TEMPLATE``, the template (:func:`fill`) filled from
    the rows the conditions keep, which must all give the same text (a JSON / YAML source without
    conditions: the whole part, one row)."""
    if len(args) < 2 or "{" not in args[-1]:
        raise SemvprError("expected '<!-- value: SOURCE [CONDITION ...] TEMPLATE -->'")
    source, *conditions, template = args
    name, _, pointer = source.partition("#")
    if Path(name).suffix in (".json", ".yaml", ".yml") and not conditions:
        path = root / name
        rows = [_document_row(pointed(read_document(path), pointer, path))]
    else:
        rows = source_rows(source, root)
    kept_by = [Condition.parse(c) for c in conditions]
    _check_fields(rows, [*(c.field for c in kept_by), *template_fields(template)], source)
    texts = {fill(template, row) for row in rows if all(c.holds(row) for c in kept_by)}
    kept = " ".join(conditions) or "no condition"
    if None in texts:
        raise SemvprError(f"{source}: {template!r} names a field that is empty in a row {kept} keeps")
    if len(texts) != 1:
        raise SemvprError(f"{source}: {kept} keeps {'no row' if not texts else 'rows that differ'} ({template!r})")
    return texts.pop()


def marker_args(text: str) -> list[str]:
    """A marker's arguments, split as a shell splits them (quotes keep spaces)."""
    try:
        return shlex.split(text)
    except ValueError as err:
        raise SemvprError(f"a marker's arguments: {err}") from None
