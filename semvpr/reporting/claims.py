"""Numbers in the committed markdown held to the data files they come from (docs/trust.md, "Numbers
in the docs").

Three invisible markers, HTML comments, tie markdown to committed CSV, JSON or YAML files (paths from the
repository root; arguments split as a shell splits them):

- ``<!-- claim: SOURCE [SOURCE ...] -->`` ... ``<!-- /claim -->``: every *result-like* number in
  between (one with a decimal point, an explicit sign, a ``%`` or a unit of time) must equal a number of
  the sources at the precision it is written with (``62.1`` matches a value in [62.05, 62.15]); a signed
  number must have the source's sign, an unsigned one may be a magnitude (``losses of 3.3 points``), and
  a percentage may be a fraction (``87.7 %`` matches ``0.877``). ``mean ± std``, ``x [low, high]`` and
  ``N of M`` (plain integers, exactly) must be adjacent fields of one record (a CSV row; a JSON / YAML
  object: any of its fields), and the numbers of one table-cell clause must all come from one record.
- ``<!-- table: SOURCE KEYS [METRICS] [OPTION=VALUE ...] -->`` ... ``<!-- /table -->``: the block is
  exactly the table :func:`~semvpr.reporting.data_rows.render_table` makes of the source
  (:class:`~semvpr.reporting.data_rows.TableSpec`).
- ``<!-- count: SOURCE CONDITION ... -->N<!-- /count -->``: a count (digits or a word) that must be the
  number of the source's rows meeting every condition (``mask=CamVid student|CamVid teacher``,
  ``gain<0``); anywhere, inside a claim too. Other plain integers (seeds, sizes, settings) are not checked.

Outside the markers a result-like number is *unsourced* (:func:`unsourced_numbers`) unless a
``NOT_RESULTS`` pattern (hyper-parameters, versions, definitions) covers it. Code spans, fenced code,
link targets and HTML comments are never read as claims.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import write_text
from semvpr.reporting.data_rows import (
    TableSpec,
    count_rows,
    marker_args,
    pointed,
    read_document,
    read_rows,
    render_table,
    stated_count,
)

#: A marker's opening comment: kind, then its arguments.
_OPEN = re.compile(r"<!--\s*(claim|table):\s*(.*?)\s*-->", re.S)
_CLOSE = {"claim": "<!-- /claim -->", "table": "<!-- /table -->"}
#: A count marker and the count it holds (in prose, within a claim or not).
_COUNT = re.compile(r"<!--\s*count:\s*(.*?)\s*-->([^<]*)<!-- /count -->", re.S)
#: A number as prose writes it: an optional sign (ASCII or typographic minus), digits with optional
#: thousands commas, optional decimals, an optional percent sign. Not part of a word (R@1, stage4, 8x,
#: 180x240, 1e-3), a version or a path.
_NUMBER = re.compile(
    r"(?<![\w@.,\-−+])(?P<sign>[+\-−](?=\d))?(?P<int>\d{1,3}(?:,\d{3})+|\d+)(?P<frac>\.\d+)?"
    r"(?P<pct>\s?%)?(?P<unit>\s(?:ms|s|min|minutes|h|hours)\b)?(?![\w@]|\.\d|,\d{3})"
)
#: A marker that starts a line with text after it: CommonMark reads that line as an HTML block.
_LINE_OPENING_MARKER = re.compile(r"^\s*<!--\s*/?(?:claim|table)\b[^>]*-->.*\S")
#: Code: fenced blocks and spans (a marker written there is an example, not a marker).
_CODE = re.compile(r"```.*?```|`[^`\n]*`", re.S)
#: Markdown that is not prose: code, HTML comments, link targets.
_NOT_PROSE = re.compile(r"```.*?```|`[^`\n]*`|<!--.*?-->|\]\([^)\s]*\)", re.S)
#: Result-like numbers that are not results (hyper-parameters, versions, definitions): each pattern's
#: whole match is allowed outside the markers, nothing else.
NOT_RESULTS = tuple(
    re.compile(p, re.M)
    for p in (
        r"^#+ .*$|§\d+(?:\.\d+)?",  # section numbers of headings and references to them
        r"(?:Python|transformers|torch) ≥? ?\d+\.\d+",  # versions
        r"95 % (?:percentile[- ])?(?:bootstrap|CI|interval)|\[95 % CI\]",  # what the intervals are
        r"thresholds? at 0\.5|≥ 0\.5",  # the binary filter's threshold
        r"≥ \+\d+ R@1|further ≥ \+\d+",  # the calibration's targets
        r"0\.98 for static(?: classes)?,? (?:and )?0\.02",  # the class weights' initial value
        r"LR\s+0\.05",  # the class weights' learning rate
        r"One query is 0\.5 points",  # the resolution of 200 queries
        r"\(x − 0\.5\)/0\.5",  # an input normalisation
        r"up to 6 hours \(the process group's timeout\), not the default 30 minutes",  # a setting
        r"about 10 minutes, so 30 epochs",  # an estimate from the work, said to be one
    )
)


def committed_docs(root: Path) -> list[Path]:
    """The markdown that states results: the front page, the docs, the experiments' and the benchmarks'
    pages."""
    pages = {root / "README.md", root / "benchmarks" / "README.md"}
    pages |= {*root.glob("docs/*.md"), *root.glob("experiments/*.md"), *root.glob("experiments/*/README.md")}
    return sorted(p for p in pages if p.is_file())


@dataclass(frozen=True)
class Stated:
    """A number as written: its value, decimals, whether it carries a sign, its text and line."""

    value: float
    decimals: int
    signed: bool
    text: str
    line: int

    @property
    def result_like(self) -> bool:
        """A decimal point, an explicit sign, a percent sign or a unit of time: what a result is written with."""
        return self.decimals > 0 or self.signed or self.text.endswith("%") or self.timed

    @property
    def timed(self) -> bool:
        """Written with a unit of time (``791 s``, ``2 h``): a measured duration."""
        return bool(re.search(r"\s(?:ms|s|min|minutes|h|hours)$", self.text))

    def matches(self, value: float) -> bool:
        """``value`` rounds to this number at its precision (sign required only if one is written)."""
        half = 0.5 * 10.0 ** (-self.decimals) + 1e-9
        if self.signed:
            return abs(value - self.value) <= half
        return abs(abs(value) - abs(self.value)) <= half

    def matches_fraction(self, value: float) -> bool:
        """A percentage matches a fraction of the source (``87.7 %`` is ``0.877``)."""
        return self.text.endswith("%") and self.matches(100.0 * value)


@dataclass(frozen=True)
class Marked:
    """One marked span of a markdown file: its kind, arguments, inner text and first line."""

    kind: str
    args: tuple[str, ...]
    text: str
    line: int
    start: int
    end: int


def _blank(match: re.Match[str]) -> str:
    """The match replaced by spaces, line breaks kept: offsets and line numbers stay."""
    return re.sub(r"[^\n]", " ", match.group(0))


def _stated(m: re.Match[str], line: int) -> Stated:
    """One number match as a :class:`Stated`."""
    sign = -1.0 if m["sign"] in ("-", "−") else 1.0
    value = sign * float(m["int"].replace(",", "") + (m["frac"] or ""))
    decimals = len(m["frac"]) - 1 if m["frac"] else 0
    return Stated(value, decimals, bool(m["sign"]), m.group(0).strip(), line)


def stated_numbers(text: str, first_line: int = 1) -> list[Stated]:
    """Every number written in the prose of ``text`` (code, comments and link targets skipped)."""
    prose = _NOT_PROSE.sub(_blank, text)
    return [_stated(m, first_line + prose.count("\n", 0, m.start())) for m in _NUMBER.finditer(prose)]


def marked_spans(markdown: str) -> list[Marked]:
    """The claim and table markers of a markdown text, in order; an unclosed or nested one is an error."""
    spans = []
    pos = 0
    code_free = _CODE.sub(_blank, markdown)  # same offsets, markers in code blanked
    while (m := _OPEN.search(code_free, pos)) is not None:
        kind, close = m[1], _CLOSE[m[1]]
        end = code_free.find(close, m.end())
        line = markdown.count("\n", 0, m.start()) + 1
        nested = _OPEN.search(code_free, m.end(), end if end >= 0 else len(markdown))
        if end < 0 or nested is not None:
            raise SemvprError(f"line {line}: '<!-- {kind}: ... -->' without its '{close}' before the next marker")
        inner = markdown[m.end() : end]
        spans.append(Marked(kind, tuple(marker_args(m[2])), inner, line, m.end(), end))
        pos = end + len(close)
    return spans


def count_spans(markdown: str) -> list[Marked]:
    """The count markers of a markdown text (inside a claim or not), in order."""
    code_free = _CODE.sub(_blank, markdown)
    return [
        Marked(
            "count",
            tuple(marker_args(m[1])),
            markdown[m.start(2) : m.end(2)],
            markdown.count("\n", 0, m.start()) + 1,
            m.start(2),
            m.end(2),
        )
        for m in _COUNT.finditer(code_free)
    ]


def _numbers_in(value: object) -> Iterable[float]:
    """Every number a CSV cell or JSON value holds (strings read for numbers too, e.g. '0 1 2')."""
    if isinstance(value, bool) or value is None:
        return
    if isinstance(value, int | float):
        if math.isfinite(value):
            yield float(value)
    elif isinstance(value, str):
        for stated in stated_numbers(value):
            yield stated.value
    elif isinstance(value, dict):
        for item in value.values():
            yield from _numbers_in(item)
    elif isinstance(value, list):
        for item in value:
            yield from _numbers_in(item)


class Record(list[float]):
    """The numbers of one source record in field order; ``ordered``: a CSV row, whose adjacent fields
    belong together (``R@1_mean, R@1_std``), not a JSON / YAML dict."""

    ordered: bool = False


def _record(values: Iterable[float], ordered: bool) -> Record:
    """A :class:`Record` of ``values``."""
    record = Record(values)
    record.ordered = ordered
    return record


def _records_in(value: object) -> Iterable[Record]:
    """Each dict of a JSON or YAML document as one record: the numbers of its direct values."""
    if isinstance(value, dict):
        own = [v for item in value.values() if not isinstance(item, dict | list) for v in _numbers_in(item)]
        if own:
            yield _record(own, ordered=False)
        for item in value.values():
            yield from _records_in(item)
    elif isinstance(value, list):
        scalars = [v for item in value if not isinstance(item, dict | list) for v in _numbers_in(item)]
        if scalars:
            yield _record(scalars, ordered=False)
        for item in value:
            yield from _records_in(item)


def source_records(source: Path) -> list[Record]:
    """The numbers of a committed data file by record: a CSV's rows, a JSON or YAML file's dicts. A JSON or
    YAML source may name a part of the file: ``results.json#/teacher/class_iou``."""
    path, _, pointer = str(source).partition("#")
    path = Path(path)
    if path.suffix == ".csv" and not pointer:
        return [_record((v for cell in row.values() for v in _numbers_in(cell)), True) for row in read_rows(path)]
    if path.suffix in (".json", ".yaml", ".yml"):
        return list(_records_in(pointed(read_document(path), pointer, path)))
    raise SemvprError(f"{source}: a claim's source must be a .csv, or a .json or .yaml file with an optional #/pointer")


def source_values(path: Path) -> list[float]:
    """Every number of a committed data file."""
    return [v for record in source_records(path) for v in record]


def _clauses(row: str) -> list[str]:
    """A markdown table row cut into its cells, and each cell at ``;`` and ``, `` outside brackets: the
    pieces whose numbers one source record must hold together (``54.5 ± 0.9 (−0.2 [−3.0, +2.5])``)."""
    pieces, depth, current = [], 0, []
    for i, char in enumerate(row):
        depth += char in "([" and 1 or 0
        depth -= char in ")]" and 1 or 0
        if depth <= 0 and (char == "|" or char == ";" or (char == "," and row[i + 1 : i + 2] == " ")):
            pieces.append("".join(current))
            current = []
            depth = 0
        else:
            current.append(char)
    pieces.append("".join(current))
    return [piece for piece in pieces if piece.strip()]


def check_markdown(path: Path, root: Path) -> list[str]:
    """What does not hold in one markdown file: a number in a claim that no source has, a generated
    table that differs from its source, a count that its source's rows do not give, a marker naming a
    file that is not there."""
    markdown = path.read_text(encoding="utf-8")
    where = str(path.relative_to(root)) if path.is_relative_to(root) else str(path)
    problems = [
        f"{where}:{n}: a marker opens this line of text, which would render as raw HTML (move it up a line)"
        for n, line in enumerate(markdown.splitlines(), 1)
        if _LINE_OPENING_MARKER.match(line)
    ]
    for span in marked_spans(markdown):
        try:
            problems += _check_span(span, root, where)
        except SemvprError as err:  # a marker or source that cannot be read: this one marker's problem
            problems.append(f"{where}:{span.line}: {err}")
    for span in count_spans(markdown):
        try:
            stated, counted = stated_count(span.text), count_rows(span.args, root)
        except SemvprError as err:
            problems.append(f"{where}:{span.line}: {err}")
            continue
        if stated != counted:
            problems.append(
                f"{where}:{span.line}: {span.text.strip()!r} is not the {counted} rows of {' '.join(span.args)}"
            )
    return problems


def _holds(stated: Stated, record: Sequence[float]) -> bool:
    """The number is one of the record's, at its precision (a percentage also as a fraction); a plain
    integer (a count) exactly."""
    if not stated.result_like:
        return stated.value in record
    return any(stated.matches(v) or stated.matches_fraction(v) for v in record)


def _chains(text: str, first_line: int) -> list[list[Stated]]:
    """Numbers written as one value: ``mean ± std``, ``estimate [low, high]`` and a count ``N of M``; a data
    file keeps them in adjacent fields (``R@1_mean, R@1_std``; ``gain, ci_low, ci_high``; ``{"mean", "stderr"}``;
    ``seeds_better, seeds``)."""
    prose = _NOT_PROSE.sub(_blank, text)
    matches = list(_NUMBER.finditer(prose))
    chains, i = [], 0
    while i < len(matches):
        end = i
        gaps = [prose[matches[k].end() : matches[k + 1].start()] for k in range(i, len(matches) - 1)]
        if gaps[:1] == [" ± "] or (
            gaps[:1] == [" of "] and not _result_like(matches[i]) and not _result_like(matches[i + 1])
        ):
            end = i + 1
        elif len(gaps) >= 2 and gaps[0] == " [" and gaps[1] == ", " and prose[matches[i + 2].end()] == "]":
            end = i + 2
        if end > i:
            chains.append([_stated(m, first_line + prose.count("\n", 0, m.start())) for m in matches[i : end + 1]])
        i = end + 1
    return chains


def _result_like(m: re.Match[str]) -> bool:
    """A number match written as a result (not a plain integer)."""
    return _stated(m, 0).result_like


def _in_sequence(chain: list[Stated], record: Record) -> bool:
    """The chain's numbers are consecutive values of a CSV row, in order, or values of one JSON / YAML
    dict (whose key order means nothing)."""
    if not record.ordered:
        return all(_holds(s, record) for s in chain)
    return any(
        all(_holds(s, record[start + k : start + k + 1]) for k, s in enumerate(chain))
        for start in range(len(record) - len(chain) + 1)
    )


def _check_span(span: Marked, root: Path, where: str) -> list[str]:
    """What does not hold in one table or claim marker's span."""
    if span.kind == "table":
        if span.text.strip() != render_table(TableSpec.of_marker(span.args, root), root):
            return [f"{where}:{span.line}: table differs from {span.args[0]} (regenerate it)"]
        return []
    if not span.args:
        return [f"{where}:{span.line}: a claim names no source"]
    return _check_claim(span, [r for source in span.args for r in source_records(root / source)], where)


def _check_claim(span: Marked, records: list[Record], where: str) -> list[str]:
    """A claim's numbers against its sources' records: each number in some record, and the numbers of one
    table-cell clause (``70.6 ± 1.3``, ``−0.2 [−3.0, +2.5]``) all in the same record."""
    sources = ", ".join(span.args)
    problems = []
    for stated in stated_numbers(span.text, span.line):
        if stated.result_like and not any(_holds(stated, record) for record in records):
            problems.append(f"{where}:{stated.line}: {stated.text} is in no source of its claim ({sources})")
    for chain in _chains(span.text, span.line):
        if not any(_in_sequence(chain, record) for record in records):
            numbers = " ".join(s.text for s in chain)
            problems.append(f"{where}:{chain[0].line}: {numbers} are not side by side in one record of {sources}")
    for offset, line in enumerate(span.text.split("\n")):
        if not line.lstrip().startswith("|"):
            continue
        for clause in _clauses(line):
            together = [s for s in stated_numbers(clause, span.line + offset) if s.result_like]
            if len(together) > 1 and not any(all(_holds(s, record) for s in together) for record in records):
                numbers = ", ".join(s.text for s in together)
                problems.append(f"{where}:{span.line + offset}: {numbers} are not from one record of {sources}")
    return problems


def unsourced_numbers(markdown: str, allow: Sequence[re.Pattern[str]] = NOT_RESULTS) -> list[Stated]:
    """Result-like numbers outside every marker, except where an ``allow`` pattern's match covers them."""
    marked = [(s.start, s.end) for s in marked_spans(markdown)]
    outside = "".join(
        "\n" * markdown.count("\n", start, end) if any(a <= start < b for a, b in marked) else markdown[start:end]
        for start, end in _segments(len(markdown), marked)
    )
    prose = _NOT_PROSE.sub(_blank, outside)
    covered = [(m.start(), m.end()) for pattern in allow for m in pattern.finditer(prose)]
    found = []
    for m in _NUMBER.finditer(prose):
        stated = _stated(m, 1 + prose.count("\n", 0, m.start()))
        if stated.result_like and not any(a <= m.start() and m.end() <= b for a, b in covered):
            found.append(stated)
    return found


def _segments(length: int, marked: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """[0, length) cut at the marked spans' edges: the spans themselves and what lies between them."""
    cuts = sorted({0, length, *(p for span in marked for p in span)})
    return list(zip(cuts, cuts[1:], strict=False))


def write_tables(path: Path, root: Path) -> bool:
    """Regenerate every table marker of a markdown file from its source; True if the file changed."""
    markdown = path.read_text(encoding="utf-8")
    out, pos = [], 0
    for span in marked_spans(markdown):
        if span.kind != "table":
            continue
        table = render_table(TableSpec.of_marker(span.args, root), root)
        out += [markdown[pos : span.start], "\n", table, "\n"]
        pos = span.end
    updated = "".join(out) + markdown[pos:]
    if updated != markdown:
        write_text(path, updated)
    return updated != markdown


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m semvpr.reporting.claims``."""
    ap = argparse.ArgumentParser(description="Check the numbers of the docs against their data files.")
    ap.add_argument("files", type=Path, nargs="*", help="markdown files (default: the committed docs)")
    ap.add_argument("--write", action="store_true", help="rewrite every generated table from its source first")
    ap.add_argument("--root", type=Path, default=Path("."), help="where the markers' paths start (the repository)")
    return ap


@exit_on_user_error
def main() -> None:
    """``python -m semvpr.reporting.claims [--write] [FILE ...]``: check the committed docs (or FILEs)
    against their data files, after rewriting their generated tables with ``--write``; exit 1 on a
    problem, one line each."""
    args = parser().parse_args()
    root = args.root.resolve()
    problems = []
    for path in [p.resolve() for p in args.files] or committed_docs(root):
        if args.write and write_tables(path, root):
            print(f"{path}: tables rewritten")
        problems += check_markdown(path, root)
        where = path.relative_to(root) if path.is_relative_to(root) else path
        problems += [
            f"{where}:{s.line}: {s.text} is outside every claim marker"
            for s in unsourced_numbers(path.read_text(encoding="utf-8"))
        ]
    print("\n".join(problems) or "every stated number holds")
    raise SystemExit(1 if problems else 0)


if __name__ == "__main__":
    main()
