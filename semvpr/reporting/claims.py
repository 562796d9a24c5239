"""Numbers in the committed markdown generated from the data files they come from (docs/trust.md,
"Numbers in the docs").

Three invisible markers, HTML comments, tie markdown to committed CSV, JSON or YAML files (paths from the
repository root; arguments split as a shell splits them); each holds exactly the text its source gives:

- ``<!-- value: SOURCE [CONDITION ...] TEMPLATE -->TEXT<!-- /value -->``: a number (or several written as
  one: ``+8.4 ± 2.4``, ``+3.7 [+1.4, +6.2]``) filled into TEMPLATE from the row its conditions keep
  (:func:`~semvpr.reporting.data_rows.value_text`): the file, the row and the column, named.
- ``<!-- table: SOURCE KEYS [METRICS] [OPTION=VALUE ...] -->`` ... ``<!-- /table -->``: the table
  :func:`~semvpr.reporting.data_rows.render_table` makes of the source
  (:class:`~semvpr.reporting.data_rows.TableSpec`).
- ``<!-- count: SOURCE CONDITION ... -->N<!-- /count -->``: a count (digits or a word) that must be the
  number of the source's rows meeting every condition (``mask=CamVid student|CamVid teacher``, ``gain<0``).

Outside the markers a *result-like* number (one with a decimal point, an explicit sign, a ``%`` or a
unit of time) is an error (:func:`unsourced_numbers`): a result is written only by a marker, a setting
only as code (``lr=0.05``). Code spans, fenced code, link targets, HTML comments and section
references (``§3.4``) are never read as numbers; other plain integers (sizes, seeds) are not checked.
"""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass
from pathlib import Path

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import write_text
from semvpr.reporting.data_rows import (
    TableSpec,
    count_rows,
    marker_args,
    render_table,
    stated_count,
    value_text,
)

#: A marker's opening comment: kind, then its arguments.
_OPEN = re.compile(r"<!--\s*(value|table):\s*(.*?)\s*-->", re.S)
_CLOSE = {"value": "<!-- /value -->", "table": "<!-- /table -->"}
#: A count marker and the count it holds.
_COUNT = re.compile(r"<!--\s*count:\s*(.*?)\s*-->([^<]*)<!-- /count -->", re.S)
#: A number as prose writes it: an optional sign (ASCII or typographic minus), digits with optional
#: thousands commas, optional decimals, an optional percent sign or unit of time. Not part of a word
#: (R@1, stage4, 8x, 180x240, 1e-3), a version, a path or a section reference (§3.4).
_NUMBER = re.compile(
    r"(?<![\w@.,\-−+§])(?P<sign>[+\-−](?=\d))?(?P<int>\d{1,3}(?:,\d{3})+|\d+)(?P<frac>\.\d+)?"
    r"(?P<pct>\s?%)?(?P<unit>\s(?:ms|s|min|minutes|h|hours)\b)?(?![\w@]|\.\d|,\d{3})"
)
#: A marker that starts a line with text after it: CommonMark reads that line as an HTML block.
_LINE_OPENING_MARKER = re.compile(r"^\s*<!--\s*/?(?:value|table)\b[^>]*-->.*\S")
#: Code: fenced blocks and spans (a marker written there is an example, not a marker).
_CODE = re.compile(r"```.*?```|`[^`\n]*`", re.S)
#: Markdown that is not prose: code, HTML comments, link targets, headings (their numbers are sections').
_NOT_PROSE = re.compile(r"```.*?```|`[^`\n]*`|<!--.*?-->|\]\([^)\s]*\)|^#+ [^\n]*$", re.S | re.M)


def committed_docs(root: Path) -> list[Path]:
    """The markdown that states results: the front page, the docs, the experiments' and the benchmarks'
    pages."""
    pages = {root / "README.md", root / "benchmarks" / "README.md"}
    pages |= {*root.glob("docs/*.md"), *root.glob("experiments/*.md"), *root.glob("experiments/*/README.md")}
    return sorted(p for p in pages if p.is_file())


@dataclass(frozen=True)
class Stated:
    """A number as written: its text and line."""

    text: str
    line: int

    @property
    def result_like(self) -> bool:
        """A decimal point, an explicit sign, a percent sign or a unit of time: what a result is written with."""
        return bool(re.search(r"\.\d|^[+\-−]|%$|\s(?:ms|s|min|minutes|h|hours)$", self.text))


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


def _filled(match: re.Match[str]) -> str:
    """The match's characters replaced by ``x``, line breaks kept: code that is text, not a marker."""
    return re.sub(r"[^\n]", "x", match.group(0))


def _stated(m: re.Match[str], line: int) -> Stated:
    """One number match as a :class:`Stated`."""
    return Stated(m.group(0).strip(), line)


def stated_numbers(text: str, first_line: int = 1) -> list[Stated]:
    """Every number written in the prose of ``text`` (code, comments and link targets skipped)."""
    prose = _NOT_PROSE.sub(_blank, text)
    return [_stated(m, first_line + prose.count("\n", 0, m.start())) for m in _NUMBER.finditer(prose)]


def marked_spans(markdown: str) -> list[Marked]:
    """The value and table markers of a markdown text, in order; an unclosed or nested one is an error."""
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
        args = marker_args(markdown[m.start(2) : m.end(2)])  # code in an argument kept as written
        spans.append(Marked(kind, tuple(args), inner, line, m.end(), end))
        pos = end + len(close)
    return spans


def count_spans(markdown: str) -> list[Marked]:
    """The count markers of a markdown text, in order."""
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


def check_markdown(path: Path, root: Path) -> list[str]:
    """What does not hold in one markdown file: a value or table that differs from what its source gives,
    a count that its source's rows do not give, a marker naming a file that is not there."""
    markdown = path.read_text(encoding="utf-8")
    where = str(path.relative_to(root)) if path.is_relative_to(root) else str(path)
    problems = [
        f"{where}:{n}: a marker opens this line of text, which would render as raw HTML (move it up a line)"
        for n, line in enumerate(_CODE.sub(_filled, markdown).splitlines(), 1)
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


def _check_span(span: Marked, root: Path, where: str) -> list[str]:
    """What does not hold in one table or value marker's span: its text is not what its source gives."""
    if span.kind == "table":
        if span.text.strip() != render_table(TableSpec.of_marker(span.args, root), root):
            return [f"{where}:{span.line}: table differs from {span.args[0]} (regenerate it)"]
        return []
    expected = value_text(span.args, root)
    if span.text != expected:
        return [f"{where}:{span.line}: {span.text!r} is not {expected!r}, what {span.args[0]} gives (regenerate it)"]
    return []


def unsourced_numbers(markdown: str) -> list[Stated]:
    """Result-like numbers outside every marker."""
    marked = [(s.start, s.end) for s in [*marked_spans(markdown), *count_spans(markdown)]]
    outside = "".join(
        "\n" * markdown.count("\n", start, end) if any(a <= start < b for a, b in marked) else markdown[start:end]
        for start, end in _segments(len(markdown), marked)
    )
    prose = _NOT_PROSE.sub(_blank, outside)
    found = (_stated(m, 1 + prose.count("\n", 0, m.start())) for m in _NUMBER.finditer(prose))
    return [stated for stated in found if stated.result_like]


def _segments(length: int, marked: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """[0, length) cut at the marked spans' edges: the spans themselves and what lies between them."""
    cuts = sorted({0, length, *(p for span in marked for p in span)})
    return list(zip(cuts, cuts[1:], strict=False))


def write_generated(path: Path, root: Path) -> bool:
    """Regenerate every table and value marker of a markdown file from its source; True if the file changed."""
    markdown = path.read_text(encoding="utf-8")
    out, pos = [], 0
    for span in marked_spans(markdown):
        if span.kind == "table":
            out += [markdown[pos : span.start], "\n", render_table(TableSpec.of_marker(span.args, root), root), "\n"]
        else:
            out += [markdown[pos : span.start], value_text(span.args, root)]
        pos = span.end
    updated = "".join(out) + markdown[pos:]
    if updated != markdown:
        write_text(path, updated)
    return updated != markdown


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m semvpr.reporting.claims``."""
    ap = argparse.ArgumentParser(description="Check the numbers of the docs against their data files.")
    ap.add_argument("files", type=Path, nargs="*", help="markdown files (default: the committed docs)")
    ap.add_argument("--write", action="store_true", help="rewrite every table and value from its source first")
    ap.add_argument("--root", type=Path, default=Path("."), help="where the markers' paths start (the repository)")
    return ap


@exit_on_user_error
def main() -> None:
    """``python -m semvpr.reporting.claims [--write] [FILE ...]``: check the committed docs (or FILEs)
    against their data files, after rewriting their tables and values with ``--write``; exit 1 on a
    problem, one line each."""
    args = parser().parse_args()
    root = args.root.resolve()
    problems = []
    for path in [p.resolve() for p in args.files] or committed_docs(root):
        if args.write and write_generated(path, root):
            print(f"{path}: tables and values rewritten")
        problems += check_markdown(path, root)
        where = path.relative_to(root) if path.is_relative_to(root) else path
        problems += [
            f"{where}:{s.line}: {s.text} is a result outside every value, table and count marker"
            for s in unsourced_numbers(path.read_text(encoding="utf-8"))
        ]
    print("\n".join(problems) or "every stated number holds")
    raise SystemExit(1 if problems else 0)


if __name__ == "__main__":
    main()
