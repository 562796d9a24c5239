"""A trained retriever's descriptors of a place set's database or queries: computed once per model and
image set, cached memory-mapped (artifact kind ``descriptors``), so memory does not grow with the set.

They are computed as training's validation computes them: from the feature cache
(``retrieval.features.place_features``: the frozen trunk's outputs keyed by the frozen weights and the
images, the masks by the mask source's weights and settings), so every checkpoint on the same trunk shares
one trunk pass per image set and every checkpoint with the same mask source one mask pass; the
checkpoint's trainable part and aggregator then run on them. A mask control (``retrieval.controls``) is
computed from the cached masks of the side it masks; the other side is described unmasked."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from semvpr.core.cache import build_once, state_hash
from semvpr.core.errors import SemvprError
from semvpr.core.io import open_array
from semvpr.core.precision import compute_key
from semvpr.data.places import PlaceSet
from semvpr.retrieval.control_masks import control_masks
from semvpr.retrieval.controls import NO_CONTROL, MaskControl
from semvpr.retrieval.features import MaskPass, StoreSettings, place_features
from semvpr.retrieval.recall import check_finite
from semvpr.retrieval.retriever import Retriever


def place_descriptors(
    retriever: Retriever,
    places: PlaceSet,
    side: str,
    image_size: Sequence[int],
    cache_dir: str | Path,
    storage: str = "disk",
    control: MaskControl = NO_CONTROL,
    resize: str = "bilinear",
) -> np.ndarray:
    """Descriptors (N, D) float32 of ``places``' database (``side="db"``) or queries (``"q"``), cached under
    the model's weights (the mask source's included), the mask source's settings and weighting, the images, the
    mask ``control`` (``retrieval.controls``: a side it leaves unmasked is described without a mask) and the
    arithmetic they are computed in (``precision.compute_key``: device, precision, CPU threads).
    ``storage``: where the frozen features come from: the trunk cache (``ram`` or ``disk``: built once, read
    memory-mapped, as each row is read once) or the images (``stream``: where the cache fits no budget).
    ``resize``: how the images are resized to ``image_size`` (``data.images.RESIZES``). Anonymous memory holds a
    batch at a time: the descriptors are written into their memory-mapped cache."""
    paths = places.db_paths if side == "db" else places.q_paths
    key = {
        "model": state_hash(retriever.state_dict()),
        "images": places.identity(side),
        "image_size": list(image_size),
        **compute_key(retriever.device),
    }
    if resize != "bilinear":
        key["resize"] = resize
    source = retriever.mask_source if control.masked(side) else None
    if source is not None:
        # Another mask source (or the same weights at another input size), or another control, gives other
        # descriptors.
        key["mask"] = {**source.identity(image_size), "weighting": retriever.weighting, **control.key()}
    dim = retriever.descriptor_dim

    def build(tmp: Path) -> None:
        backbone = retriever.backbone
        # Each row is read once, in order: the cache's pages serve it, where a copy in RAM would add the
        # set's trunk maps to the process's anonymous memory and the time to copy them.
        held = "disk" if storage == "ram" else storage
        settings = StoreSettings(image_size, cache_dir, held, retriever.eval_batch_size, retriever.num_workers, resize)
        masks = None if source is None else MaskPass(source, control.cached_weighting(retriever.weighting))
        features = place_features(places, backbone, settings, masks)
        store = features.db if side == "db" else features.q
        if store.mask is not None:
            store.mask = control_masks(control, store.mask, side)
        out = open_array(tmp / "descriptors.npy", np.float32, (len(paths), dim), f"the descriptors of {places.name}")
        retriever.describe_store(store, out=out)
        out.flush()
        check_finite(out, f"{places.name} {side}")  # a non-finite cache is never kept

    folder = build_once(cache_dir, "descriptors", key, build)
    try:
        desc = np.load(folder / "descriptors.npy", mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as err:
        raise SemvprError(
            f"descriptor cache {folder} is unreadable ({type(err).__name__}); delete it to rebuild"
        ) from None
    if desc.shape != (len(paths), dim) or desc.dtype != np.float32:
        raise SemvprError(
            f"descriptor cache {folder} holds {desc.dtype}{list(desc.shape)}, expected "
            f"float32[{len(paths)}, {dim}]; delete it to rebuild"
        )
    try:  # a cache is never written non-finite (build): such values were put there since
        check_finite(desc, f"{places.name} {side}")
    except SemvprError:
        raise SemvprError(f"descriptor cache {folder} holds values that are not finite; delete it to rebuild") from None
    return desc
