"""Published set sizes and Recall@N, read from ``published.yaml`` (numbers with their citations)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

from semvpr.core.errors import SemvprError
from semvpr.core.io import read_yaml

PUBLISHED = Path(__file__).with_name("published.yaml")


@lru_cache(maxsize=1)
def published() -> dict[str, Any]:
    """The whole file as plain Python (sets, results)."""
    data = read_yaml(PUBLISHED, "published numbers")
    assert isinstance(data, dict)
    return data


def check_counts(set_name: str, database: int, queries: int, where: str) -> None:
    """Refuse a recognised set whose files hold another number of images than its release."""
    expected = published()["sets"].get(set_name)
    if expected is None:
        return
    if (database, queries) != (expected["database"], expected["queries"]):
        raise SemvprError(
            f"{where}: {database} database / {queries} query images, but {set_name} has "
            f"{expected['database']} / {expected['queries']} ({expected['source']}); "
            f"the files are incomplete or of another set"
        )


def results_for(model: str, benchmark: str | None) -> list[dict[str, Any]]:
    """Published rows for a model family on a protocol (none when either is unknown)."""
    return [r for r in published()["results"] if r["model"] == model and r["benchmark"] == benchmark]
