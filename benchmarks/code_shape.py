"""How much of a package's code checks its input: code lines and guard lines, counted with Python's ``ast``.

A *code line* is a line holding a token of code (not blank, not only a comment, not inside a docstring). A
*guard line* is a code line of a ``raise`` or an ``assert``, of the test of an ``if`` whose own body raises, of an
``except`` clause whose own body raises, or of a function named ``check_*`` / ``refuse_*`` (leading ``_``
ignored). Run it over semvpr or over another project's package to compare them by one count:

    python benchmarks/code_shape.py semvpr [--by-file 10] [--json]

Prints the totals (code lines, guard lines, their share, ``raise SemvprError`` sites) and, with ``--by-file N``,
the N files with the most guard lines; ``--json`` prints the same as one JSON object.
"""

from __future__ import annotations

import argparse
import ast
import io
import json
import tokenize
from dataclasses import dataclass, field
from pathlib import Path

from semvpr.core.errors import SemvprError, exit_on_user_error

GUARD_PREFIXES = ("check_", "refuse_")
_NOT_CODE = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER}


@dataclass
class Shape:
    """One file's (or a package's) counts."""

    code: int = 0
    guards: int = 0
    semvpr_raises: int = 0
    by_file: dict[str, int] = field(default_factory=dict)

    def add(self, path: str, other: Shape) -> None:
        self.code += other.code
        self.guards += other.guards
        self.semvpr_raises += other.semvpr_raises
        self.by_file[path] = other.guards


def _lines(node: ast.AST) -> set[int]:
    return set(range(node.lineno, (node.end_lineno or node.lineno) + 1))  # type: ignore[attr-defined]


def _raises(body: list[ast.stmt]) -> bool:
    """Whether a block raises at its own level (not in a nested function)."""
    return any(isinstance(s, ast.Raise) for s in body)


def _docstring_lines(tree: ast.AST) -> set[int]:
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            value = first.value if isinstance(first, ast.Expr) else None
            if isinstance(value, ast.Constant) and isinstance(value.value, str):
                lines |= _lines(first)
    return lines


def shape_of(source: str) -> Shape:
    """The counts of one module's source."""
    tree = ast.parse(source)
    docstrings = _docstring_lines(tree)
    code = {
        line
        for tok in tokenize.generate_tokens(io.StringIO(source).readline)
        if tok.type not in _NOT_CODE
        for line in range(tok.start[0], tok.end[0] + 1)
    } - docstrings
    guards: set[int] = set()
    semvpr_raises = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.Raise | ast.Assert):
            guards |= _lines(node)
            exc = node.exc if isinstance(node, ast.Raise) else None
            call = exc.func if isinstance(exc, ast.Call) else exc
            semvpr_raises += isinstance(call, ast.Name) and call.id == "SemvprError"
        elif isinstance(node, ast.If) and _raises(node.body):
            guards |= _lines(node.test)
        elif isinstance(node, ast.ExceptHandler) and _raises(node.body):
            guards.add(node.lineno)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name.lstrip("_").startswith(
            GUARD_PREFIXES
        ):
            guards |= _lines(node)
    return Shape(code=len(code), guards=len(guards & code), semvpr_raises=semvpr_raises)


def package_shape(root: Path) -> Shape:
    """The counts over every ``.py`` file under ``root``."""
    files = sorted(root.rglob("*.py")) if root.is_dir() else [root]
    if not files:
        raise SemvprError(f"{root}: no Python files")
    total = Shape()
    for path in files:
        try:
            total.add(str(path), shape_of(path.read_text(encoding="utf-8")))
        except (SyntaxError, UnicodeDecodeError) as err:
            raise SemvprError(f"{path}: cannot parse: {err}") from None
    return total


@exit_on_user_error
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="a package folder (or one .py file)")
    parser.add_argument("--by-file", type=int, default=0, metavar="N", help="the N files with the most guard lines")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    shape = package_shape(args.root)
    share = 100 * shape.guards / max(shape.code, 1)
    top = sorted(shape.by_file.items(), key=lambda kv: -kv[1])[: args.by_file]
    if args.json:
        out = {"root": str(args.root), "code_lines": shape.code, "guard_lines": shape.guards, "guard_share": share}
        print(json.dumps({**out, "semvpr_error_raises": shape.semvpr_raises, "top": dict(top)}))
        return
    print(f"{args.root}: {shape.code} code lines, {shape.guards} guard lines ({share:.1f} %), ", end="")
    print(f"{shape.semvpr_raises} raise SemvprError sites")
    for path, guards in top:
        print(f"  {guards:5d}  {path}")


if __name__ == "__main__":
    main()
