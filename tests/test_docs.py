"""Every ``ARCHITECTURE §n`` cited in the code names a section that docs/ARCHITECTURE.md has."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_architecture_references_resolve() -> None:
    doc = (REPO / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    sections = set(re.findall(r"^#{2,3} (\d+(?:\.\d+)?)\.? ", doc, flags=re.M))
    cited: dict[str, list[str]] = {}
    for path in [*REPO.glob("semvpr/**/*.py"), *REPO.glob("conf/**/*.yaml"), *REPO.glob("benchmarks/*.py")]:
        for ref in re.findall(r"ARCHITECTURE §(\d+(?:\.\d+)?)", path.read_text(encoding="utf-8")):
            cited.setdefault(ref, []).append(str(path.relative_to(REPO)))
    assert cited, "the code cites no section: the doc would be unreachable from it"
    missing = {ref: where for ref, where in cited.items() if ref not in sections}
    assert not missing, f"sections cited but absent from docs/ARCHITECTURE.md: {missing}"


def _imported_modules(path: Path) -> set[str]:
    """Absolute semvpr modules a file imports (``from semvpr.x import y`` counts x and x.y)."""
    import ast

    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found |= {node.module, *(f"{node.module}.{alias.name}" for alias in node.names)}
    return {name for name in found if name.startswith("semvpr")}


def test_no_module_imports_an_entry_point() -> None:
    """ARCHITECTURE §1: what two commands share lives below them, never in a command's module."""
    doc = (REPO / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    commands = set(re.findall(r"^\| `python -m (semvpr\.[\w.]+)", doc, flags=re.M))
    # Modules that are a library first and also runnable (a generator, a summary) are not thin commands.
    entry_points = commands - {"semvpr.data.synthcity", "semvpr.data.inspect"}
    assert {"semvpr.train", "semvpr.eval", "semvpr.report"} <= entry_points, commands
    offenders = {}
    for path in REPO.glob("semvpr/**/*.py"):
        module = ".".join(path.relative_to(REPO).with_suffix("").parts)
        bad = (_imported_modules(path) & entry_points) - {module}
        if bad:
            offenders[module] = sorted(bad)
    assert not offenders, f"modules importing an entry point (move the shared code below it): {offenders}"
