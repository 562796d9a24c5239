"""Mask controls: what a mask's content is replaced by, and which side of a place set it weights.

A control is a setting of any mask source and any aggregator (``mask.control``, ``mask.apply``,
``mask.control_seed``; docs/evaluation.md). It is computed from the cached grid masks of a side's images
(``retrieval.features``), so it costs no trunk or segmenter pass of its own:

- ``none``: the source's own mask;
- ``objects``: only the dynamic object classes (person ... bicycle) removed, the sky kept;
- ``sky``: only the sky removed;
- ``random``: as many cells of each image removed as the source's own mask removes from it, drawn at random;
- ``shuffled``: each image weighted by the source's mask of another image of the same side (a derangement).

``objects`` and ``sky`` read the source's class probabilities pooled to the grid (the cache that
``mask.weights=learned`` reads): a cell is removed where the removed classes' pooled probability exceeds 0.5,
as the binary filter removes a cell where the non-static classes' does. ``random`` and ``shuffled`` draw from
``control_seed``, the database's draws apart from the queries'.

``apply``: ``both`` sides, or only the ``database``'s or the ``queries``' images; the other side is described
unmasked.

What a control is lives here, without torch (the reports read it); ``retrieval.control_masks`` computes its
masks.
"""

from __future__ import annotations

from dataclasses import dataclass

from semvpr.data.classes import TRAIN_ID_NAMES

CONTROLS = ("none", "objects", "sky", "random", "shuffled")
APPLIES = ("both", "database", "queries")
#: The Cityscapes train ids each class control removes.
REMOVED_CLASSES: dict[str, tuple[int, ...]] = {
    "objects": tuple(range(TRAIN_ID_NAMES.index("person"), len(TRAIN_ID_NAMES))),
    "sky": (TRAIN_ID_NAMES.index("sky"),),
}
#: The side each ``apply`` value leaves masked ("db", "q": a place set's sides).
_SIDES = {"both": ("db", "q"), "database": ("db",), "queries": ("q",)}


@dataclass(frozen=True)
class MaskControl:
    """A mask control (see the module docstring): ``control``, the sides it ``apply``s to and its ``seed``."""

    control: str = "none"
    apply: str = "both"
    seed: int = 0

    @property
    def active(self) -> bool:
        """Whether it changes anything: another content, or only one side masked."""
        return self.control != "none" or self.apply != "both"

    @property
    def needs_classes(self) -> bool:
        """Whether it reads the class probabilities pooled to the grid (``objects``, ``sky``)."""
        return self.control in REMOVED_CLASSES

    def masked(self, side: str) -> bool:
        """Whether the images of ``side`` (``db`` or ``q``) are weighted by the mask."""
        return side in _SIDES[self.apply]

    def cached_weighting(self, weighting: str) -> str:
        """The weighting of the cached masks it is computed from (``learned``: the pooled class probabilities)."""
        return "learned" if self.needs_classes else weighting

    def key(self) -> dict[str, object]:
        """What a side's masked descriptors depend on beyond the source's masks (empty for ``none``)."""
        if self.control == "none":
            return {}
        drawn = self.control in ("random", "shuffled")
        return {"control": self.control, **({"control_seed": self.seed} if drawn else {})}

    def label(self) -> str:
        """How a table names it beside the mask: empty for the source's own mask on both sides."""
        parts = []
        if self.control != "none":
            drawn = self.control in ("random", "shuffled")
            parts.append(f"control={self.control}" + (f" (seed {self.seed})" if drawn else ""))
        if self.apply != "both":
            parts.append(f"on the {self.apply} only")
        return ", ".join(parts)


#: The source's own mask on both sides.
NO_CONTROL = MaskControl()
