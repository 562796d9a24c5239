"""Where a segmenter was trained: the data set's name and its kind of images (ARCHITECTURE §3.2).

A mask source is only as good on an image as its segmenter is on images of that kind: one trained on
SynthCity's renders, applied to real frames, removes places with the people. Training checkpoints,
teacher directories and student directories carry this record, so that an evaluation on another kind
of data can say so. It is read from files written by others: every value is checked (plain strings, a
known kind, one short line), never run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from semvpr.core.errors import SemvprError

#: The kinds of images a segmenter can have been trained on; "unknown" for weights from elsewhere.
DOMAINS = ("synthetic", "real", "unknown")
_MAX_NAME = 120


@dataclass(frozen=True)
class TrainedOn:
    """A segmenter's training data: ``name`` (e.g. ``synthcity``, ``camvid``, a Hub id) and ``domain``."""

    name: str
    domain: str = "unknown"

    def __post_init__(self) -> None:
        if self.domain not in DOMAINS:
            raise SemvprError(f"trained_on.domain={self.domain!r} is not one of {list(DOMAINS)}")

    def as_dict(self) -> dict[str, str]:
        """The JSON form a checkpoint or a segmenter directory stores."""
        return {"name": self.name, "domain": self.domain}

    def describe(self) -> str:
        """``name (domain images)`` for one-line messages."""
        return f"{self.name} ({self.domain} images)"

    @classmethod
    def from_value(cls, value: Any, where: str) -> TrainedOn:
        """Read a stored record, refusing anything but ``{"name": str, "domain": one of DOMAINS}``."""
        if not isinstance(value, dict) or set(value) != {"name", "domain"}:
            raise SemvprError(f"{where}: expected {{'name': ..., 'domain': ...}}, got {_short(value)}")
        name, domain = value["name"], value["domain"]
        if not isinstance(name, str) or not name.strip() or len(name) > _MAX_NAME or not name.isprintable():
            raise SemvprError(f"{where}.name={_short(name)} is not a short printable name")
        if domain not in DOMAINS:
            raise SemvprError(f"{where}.domain={_short(domain)} is not one of {list(DOMAINS)}")
        return cls(name, domain)


def data_domain(domain: Any) -> str:
    """The kind of images a data config holds (its ``domain`` key; a set that does not say is real)."""
    return "real" if domain is None else str(domain)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
