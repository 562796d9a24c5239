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
