"""What the frozen networks give per image: the frozen trunk's output and the static grid mask.

Below ``backbone.train_from`` nothing learns, so the frozen prefix's output (the *trunk* features)
and the mask (which depends only on the image and frozen networks) are computed once per image and
reused by every epoch, by mining and by every sweep job with the same frozen weights (artifact kinds
``trunk`` / ``masks``, ``.npy`` files written batch by batch, never gathered in RAM).

How the trunk cache is held is chosen by its size (``features.storage``, ARCHITECTURE §5: at 480x640 a
VGG16 pool4 map is 1.2 MB in bf16, Pitts30k's three splits ~64 GB):

- ``ram``: it fits ``features.ram_gb``: read into memory;
- ``disk``: it fits ``features.disk_gb`` and the free disk, less a headroom (``DISK_HEADROOM``): memory-mapped,
  pages read on demand;
- ``stream``: neither: nothing is cached but the masks; images go through the frozen prefix at
  every use, as pytorch-NetVlad does (mining keeps only descriptors).

The three give the same features; only speed and memory differ. ``ram`` is for the stores a run reads many
times (training's epochs, mining, validation); a checkpoint's descriptors (``retrieval.descriptors``) read each
row once and map the cache whichever of ``ram`` and ``disk`` was chosen, so that no process holds the set's maps
in anonymous memory only to read them once.

Where the semantic side reads the frozen prefix too (the student's skips; a teacher whose pixel encoder is
the trunk, ``Teacher.link_trunk``), the same pass also keeps those outputs (artifact kind ``skips``, one per
output level), so that each image goes through the frozen weights once: pseudo-labels, the student's
training features and the teacher's or student's masks are then computed from the cache.
"""

from __future__ import annotations

import math
import shutil
import weakref
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from semvpr.core.cache import artifact_dir, build_once
from semvpr.core.errors import SemvprError
from semvpr.core.io import open_array, temp_dir
from semvpr.core.logs import Progress, progress
from semvpr.core.precision import autocast
from semvpr.core.threads import frozen_pass
from semvpr.data.classes import NUM_CLASSES
from semvpr.data.images import ImageDataset, read_image, to_unit
from semvpr.data.places import PlaceSet
from semvpr.models.masks import MaskSource
from semvpr.retrieval.loading import loader_settings

STORAGES = ("auto", "ram", "disk", "stream")
DISK_HEADROOM = 2 * 2**30
"""Bytes a new disk cache leaves free (a tenth of the disk where that is less): a fixed margin, so that whether a
small cache fits never depends on how full a large shared disk happens to be."""
#: Trunk features are bf16 wherever they come from (cache or stream), so every path gives the same
#: descriptors, and the cache is half the size.
TRUNK_DTYPE = torch.bfloat16
GiB = 2**30


@dataclass
class FeatureStore:
    """Per-image inputs of the trainable part for one image list.

    ``trunk`` (N,C,h',w') bf16 in RAM or memory-mapped, or None when streamed (then items are
    images and the module runs the frozen prefix); ``mask`` the grid masks or None: (N,1,h,w)
    binary, or (N,C,h,w) class probabilities for learned class weights (semvpr.models.masks).
    """

    paths: tuple[Path, ...]
    image_size: tuple[int, int]
    trunk: Tensor | None
    mask: Tensor | None
    #: Other frozen outputs kept by the trunk pass, by their index in ``forward_frozen(x)``: (N,C,h,w) bf16.
    skips: dict[int, Tensor] = field(default_factory=dict)
    #: The trunk's index in ``forward_frozen(x)`` (its last output).
    trunk_level: int = -1
    #: How streamed images are resized to ``image_size`` (``data.images.RESIZES``).
    resize: str = "bilinear"
    #: The trunk and masks copied to a GPU once (:func:`store_batches`), by device.
    on_device: dict[torch.device, tuple[Tensor, Tensor | None]] = field(default_factory=dict, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.paths)

    @property
    def streams(self) -> bool:
        """Whether items are images (the frozen prefix runs at every use)."""
        return self.trunk is None

    def item(self, i: int) -> dict[str, Tensor]:
        """{"trunk": (C,h',w')} or {"image": (3,H,W) as ``read_image`` gives it, made floats on the device by
        ``to_unit``}, plus "mask" ((1,h,w) or empty)."""
        if self.trunk is None:
            x = {"image": read_image(self.paths[i], self.image_size, self.resize)}
        else:
            x = {"trunk": self.trunk[i]}
        x["mask"] = self.mask[i].float() if self.mask is not None else torch.empty(0)
        return x

    @torch.no_grad()
    def trunk_of(self, index: Sequence[int], backbone: nn.Module) -> Tensor:
        """Trunk features of a few images (cached rows, or the frozen prefix on the images)."""
        if self.trunk is not None:
            return torch.stack([self.trunk[int(i)] for i in index])
        images = torch.stack([read_image(self.paths[int(i)], self.image_size, self.resize) for i in index])
        device = next(backbone.parameters()).device
        with autocast(device), frozen_pass():
            out = backbone.forward_frozen(
                to_unit(images.to(device)).contiguous(memory_format=torch.channels_last), keep_scales=False
            )[-1]
        return out.to(TRUNK_DTYPE)

    def levels(self) -> set[int]:
        """The ``forward_frozen`` output levels this store holds."""
        return set(self.skips) | ({self.trunk_level} if self.trunk is not None else set())

    def outputs(self, index: Sequence[int], levels: Sequence[int]) -> list[Tensor | None]:
        """The cached ``forward_frozen`` outputs ``levels`` of the rows ``index`` as a list shaped like
        ``forward_frozen``'s (None at the levels not asked for), channels-last as the trunk pass gives them
        (a layer reading them rounds as it would on that pass's outputs)."""
        rows = torch.from_numpy(np.asarray(index, dtype=np.int64))
        out: list[Tensor | None] = [None] * (self.trunk_level + 1)
        for level in levels:
            held = self.trunk if level == self.trunk_level else self.skips[level]
            out[level] = held[rows].contiguous(memory_format=torch.channels_last)
        return out


class StoreDataset(Dataset):
    """The items of a feature store (optionally a subset of it)."""

    def __init__(self, store: FeatureStore, index: Sequence[int] | None = None) -> None:
        self.store = store
        self.index = list(range(len(store))) if index is None else [int(i) for i in index]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return self.store.item(self.index[i])


def store_loader(
    store: FeatureStore,
    batch_size: int,
    num_workers: int,
    index: Sequence[int] | None = None,
    device: torch.device | str = "cpu",
) -> DataLoader:
    """Batches of a store in order, for a pass on ``device`` (workers and pinned memory as
    :func:`semvpr.retrieval.loading.loader_settings` gives them)."""
    settings = loader_settings(num_workers, store.streams, device)
    return DataLoader(StoreDataset(store, index), batch_size=batch_size, **settings)


#: The share of a GPU's free memory a cached store may take there to stay on it across passes.
GPU_STORE_SHARE = 0.25


def kept_on(store: FeatureStore, device: torch.device) -> tuple[Tensor, Tensor | None] | None:
    """A cached store's trunk and masks on ``device``, copied there at its first pass, where it is a GPU and they
    fit ``GPU_STORE_SHARE`` of its free memory (every later pass reads them there: no copy per batch); None
    where they stay on the host."""
    if device.type != "cuda" or store.trunk is None:
        return None
    if device not in store.on_device:
        size = store.trunk.nbytes + (store.mask.nbytes if store.mask is not None else 0)
        if size > GPU_STORE_SHARE * torch.cuda.mem_get_info(device)[0]:
            return None
        mask = store.mask.to(device) if store.mask is not None else None
        store.on_device[device] = (store.trunk.to(device), mask)
    return store.on_device[device]


def store_batches(
    store: FeatureStore,
    batch_size: int,
    num_workers: int,
    index: Sequence[int] | None = None,
    device: torch.device | str = "cpu",
) -> Iterator[dict[str, Tensor]]:
    """Batches of a store in order on ``device``, as :func:`store_loader`'s are collated: from the copy a GPU
    keeps (:func:`kept_on`) or read through the loader and copied without blocking."""
    device = torch.device(device)
    kept = kept_on(store, device)
    if kept is None:
        for batch in store_loader(store, batch_size, num_workers, index, device):
            yield {k: v.to(device, non_blocking=True) for k, v in batch.items()}
        return
    trunk, mask = kept
    rows = torch.arange(len(store), device=device) if index is None else torch.as_tensor(index, device=device)
    for part in rows.split(batch_size):
        masks = mask[part].float() if mask is not None else torch.empty((len(part), 0), device=device)
        yield {"trunk": trunk[part], "mask": masks}


@dataclass
class PlaceFeatures:
    """A place set with the feature stores of its database and queries."""

    places: PlaceSet
    db: FeatureStore
    q: FeatureStore


_SHAPES: weakref.WeakKeyDictionary[nn.Module, dict[tuple[int, int], tuple[tuple[int, ...], ...]]] = (
    weakref.WeakKeyDictionary()
)


@torch.no_grad()
def _shapes(backbone: nn.Module, image_size: Sequence[int]) -> tuple[tuple[int, ...], ...]:
    """(frozen output (C,h',w'), local features (C,h,w)) at this image size, probed once per backbone."""
    size = (int(image_size[0]), int(image_size[1]))
    known = _SHAPES.setdefault(backbone, {})
    if size not in known:
        # Eval mode: a probe in train mode would move BatchNorm statistics of a trainable ResNet stage.
        was_training = backbone.training
        backbone.eval()
        probe = torch.zeros(1, 3, *size, device=next(backbone.parameters()).device)
        frozen = backbone.forward_frozen(probe, keep_scales=False)[-1]
        known[size] = (tuple(frozen.shape[1:]), tuple(backbone.forward_trainable(frozen).shape[1:]))
        backbone.train(was_training)
    return known[size]


def grid_size(backbone: nn.Module, image_size: Sequence[int]) -> tuple[int, int]:
    """Local-feature grid (h, w) of the backbone at this image size."""
    return _shapes(backbone, image_size)[1][-2:]  # type: ignore[return-value]


def trunk_shape(backbone: nn.Module, image_size: Sequence[int]) -> tuple[int, int, int]:
    """(C, h', w') of the frozen prefix's output at this image size."""
    return _shapes(backbone, image_size)[0]  # type: ignore[return-value]


def choose_storage(
    setting: str, trunk_bytes: int, cache_dir: str | Path, ram_gb: float, disk_gb: float, cached: bool = False
) -> str:
    """``ram`` / ``disk`` / ``stream`` for a trunk cache of ``trunk_bytes`` (see the module docstring)."""
    if setting not in STORAGES:
        raise SemvprError(f"features.storage={setting!r} is not one of {list(STORAGES)}")
    if setting != "auto":
        return setting
    if trunk_bytes <= ram_gb * GiB:
        return "ram"
    Path(cache_dir).mkdir(parents=True, exist_ok=True)
    # An existing cache needs no room; a new one leaves the headroom free.
    usage = shutil.disk_usage(cache_dir)
    room = math.inf if cached else usage.free - min(DISK_HEADROOM, 0.1 * usage.total)
    return "disk" if trunk_bytes <= min(disk_gb * GiB, room) else "stream"


@dataclass(frozen=True)
class StoreSettings:
    """How a place set's stores are made and held: the image size, the artifact cache, the storage (``ram``,
    ``disk`` or ``stream``: :func:`choose_storage` decides ``auto``), the frozen pass's loader and how it resizes
    the images (``data.images.RESIZES``)."""

    image_size: tuple[int, int]
    cache_dir: Path
    storage: str
    batch_size: int = 32
    num_workers: int = 2
    resize: str = "bilinear"

    def __post_init__(self) -> None:
        if self.storage not in ("ram", "disk", "stream"):
            raise SemvprError(
                f"feature storage {self.storage!r} must be ram, disk or stream (choose_storage decides 'auto')"
            )
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))
        object.__setattr__(self, "cache_dir", Path(self.cache_dir))


@dataclass(frozen=True)
class MaskPass:
    """The grid masks a store holds: their source and weighting (``binary`` or per-class ``learned``)."""

    source: MaskSource
    weighting: str = "binary"


#: One side of a place set: its image paths and (for the oracle) label maps.
Side = tuple[Sequence[Path], Sequence[Path] | None]


class HostWrites:
    """Rows of device tensors written into host arrays. On a GPU each chunk's copies are started without
    blocking (into pinned memory) and written once they are done, after the next chunk's work is queued, so
    that they overlap it; on the CPU they are written at once."""

    def __init__(self, device: torch.device) -> None:
        self.gpu = device.type == "cuda"
        self.queued: list[tuple[np.ndarray, slice, Tensor]] = []
        self.copying: tuple[torch.cuda.Event, list[tuple[np.ndarray, slice, Tensor]]] | None = None

    def put(self, array: np.ndarray, rows: slice, tensor: Tensor) -> None:
        """Write ``tensor`` into ``array[rows]`` (cast to the array's dtype as NumPy casts)."""
        if not self.gpu:
            array[rows] = tensor.numpy()
            return
        self.queued.append((array, rows, tensor.to("cpu", non_blocking=True)))

    def chunk_done(self) -> None:
        """The chunk's copies are all started: write the previous chunk's (their end waited for)."""
        if not self.gpu:
            return
        event = torch.cuda.Event()
        event.record()
        self._write_copied()
        self.copying, self.queued = (event, self.queued), []

    def flush(self) -> None:
        """Write every copy started so far (their end waited for)."""
        if self.queued:
            self.chunk_done()
        self._write_copied()

    def _write_copied(self) -> None:
        if self.copying is None:
            return
        event, writes = self.copying
        event.synchronize()
        for array, rows, host in writes:
            array[rows] = host.numpy()
        self.copying = None


@torch.no_grad()
def _extract(
    backbone: nn.Module,
    side: Side,
    settings: StoreSettings,
    outs_to: dict[int, np.ndarray],
    masks: MaskPass | None,
    mask_out: np.ndarray | None,
    desc: str,
) -> None:
    """One pass over the images, writing frozen outputs (bf16 bits, ``outs_to``: by ``forward_frozen`` level; the
    trunk is the last) and grid masks into the arrays (``mask_out``, where ``masks`` is given)."""
    paths, labels = side
    image_size = settings.image_size
    grid = grid_size(backbone, image_size)
    device = next(backbone.parameters()).device
    wanted = masks.source.trunk_levels(image_size) if masks is not None else ()
    keep = bool(wanted) or any(level != _last_level(backbone) for level in outs_to)
    run_backbone = bool(outs_to) or bool(wanted)
    # Chunks of images whose frozen-prefix activations (and kept skips) fit the backbone's budget.
    step = backbone.images_per_forward(image_size, keep_scales=keep, device=device)
    loader = DataLoader(
        ImageDataset(list(paths), image_size, settings.resize, eight_bit=True),  # made floats on the device
        batch_size=settings.batch_size,
        num_workers=settings.num_workers,
        pin_memory=device.type == "cuda",  # copied while the device works on the chunk before
    )
    backbone.eval()
    writes = HostWrites(device)
    for batch, index in progress(loader, desc, len(paths), size=lambda b: len(b[1])):
        for start in range(0, len(index), step):
            images = to_unit(batch[start : start + step].to(device, non_blocking=True))
            images = images.contiguous(memory_format=torch.channels_last)
            first = int(index[start])
            rows = slice(first, first + len(images))
            with autocast(device):
                outs = backbone.forward_frozen(images, keep_scales=keep) if run_backbone else []
                if masks is not None and mask_out is not None:
                    chunk_labels = [labels[int(i)] for i in index[start : start + step]] if labels is not None else None
                    mask = masks.source.grid_mask(images, outs, chunk_labels, grid, masks.weighting)
                    writes.put(mask_out, rows, mask)
            for level, arr in outs_to.items():
                writes.put(arr, rows, outs[level if keep else -1].to(TRUNK_DTYPE).view(torch.uint16))
            writes.chunk_done()
    writes.flush()


def _last_level(backbone: nn.Module) -> int:
    """The index of the trunk (the trainable part's input) among ``forward_frozen(x)``'s outputs."""
    return len(backbone.frozen_strides) - 1


@torch.no_grad()
def _masks_from_cache(
    backbone: nn.Module,
    masks: MaskPass,
    store: FeatureStore,
    labels: Sequence[Path] | None,
    mask_out: np.ndarray,
    batch_size: int,
    desc: str,
) -> None:
    """Grid masks of a store's images from its cached frozen outputs (or label maps): no image is read."""
    size = store.image_size
    grid = grid_size(backbone, size)
    device = next(backbone.parameters()).device
    levels = masks.source.trunk_levels(size)
    bar = Progress(desc, len(store))
    for first in range(0, len(store), batch_size):
        index = list(range(first, min(first + batch_size, len(store))))
        outs = [o.to(device) if o is not None else None for o in store.outputs(index, levels)]
        chunk_labels = [labels[i] for i in index] if labels is not None else None
        with autocast(device):
            mask = masks.source.grid_mask(None, outs, chunk_labels, grid, masks.weighting, out_hw=size)
        mask_out[first : first + len(index)] = mask.cpu().numpy()
        bar.update(len(index))
    bar.close()


def _open(path: Path, shape: tuple[int, ...], dtype: Any, what: Path) -> np.ndarray:
    """Memory-map a cached array, checking it is what its key says (a cache may come from elsewhere)."""
    try:
        arr = np.load(path, mmap_mode="c", allow_pickle=False)
    except (OSError, ValueError) as err:
        raise SemvprError(f"feature cache {path} is unreadable ({err}); delete {what} to rebuild it") from None
    if arr.shape != shape or arr.dtype != np.dtype(dtype):
        raise SemvprError(
            f"feature cache {path} holds {arr.dtype}{list(arr.shape)}, expected "
            f"{np.dtype(dtype)}{list(shape)}; delete {what} to rebuild it"
        )
    return arr


def _data_key(places: PlaceSet, size: tuple[int, int], resize: str) -> dict[str, Any]:
    """What the features of a place set are made of: each side's images (and labels) by name and content, at
    ``size`` resized as ``resize`` says (the default, bilinear, unnamed)."""
    key = {"db": places.identity("db"), "q": places.identity("q"), "image_size": list(size)}
    return key if resize == "bilinear" else {**key, "resize": resize}


def trunk_cached(
    places: PlaceSet, backbone_key: Any, image_size: Sequence[int], cache_dir: str | Path, resize: str
) -> bool:
    """Whether this place set's trunk cache exists already."""
    size = (int(image_size[0]), int(image_size[1]))
    data = _data_key(places, size, resize)
    return artifact_dir(cache_dir, "trunk", {"backbone": backbone_key, "data": data}).is_dir()


def skip_shape(backbone: nn.Module, image_size: Sequence[int], level: int) -> tuple[int, int, int]:
    """(C, h, w) of the frozen output ``level`` at this image size (probed once)."""
    size = (int(image_size[0]), int(image_size[1]))
    known = _SKIP_SHAPES.setdefault(backbone, {})
    if size not in known:
        was_training = backbone.training
        backbone.eval()
        with torch.no_grad():
            probe = torch.zeros(1, 3, *size, device=next(backbone.parameters()).device)
            known[size] = tuple(tuple(o.shape[1:]) for o in backbone.forward_frozen(probe, keep_scales=True))
        backbone.train(was_training)
    return known[size][level]  # type: ignore[return-value]


_SKIP_SHAPES: weakref.WeakKeyDictionary[nn.Module, dict[tuple[int, int], tuple[tuple[int, ...], ...]]] = (
    weakref.WeakKeyDictionary()
)


def skip_bytes(backbone: nn.Module, image_size: Sequence[int], levels: Sequence[int], images: int) -> int:
    """Bytes of a ``skips`` cache of these levels (bf16) for this many images."""
    return sum(2 * images * int(np.prod(skip_shape(backbone, image_size, level))) for level in levels)


@dataclass(frozen=True)
class _Kind:
    """One cached array per side: its artifact kind and key, per-image shape and dtype."""

    kind: str
    key: Any
    shape: tuple[int, ...]
    dtype: Any
    level: int | None = None  # the forward_frozen output it holds (trunk and skips)


def place_features(
    places: PlaceSet,
    backbone: nn.Module,
    settings: StoreSettings,
    masks: MaskPass | None = None,
    skip_levels: Sequence[int] = (),
) -> PlaceFeatures:
    """Feature stores of a place set: trunk (unless streamed), the frozen outputs ``skip_levels`` and masks from
    the cache, built once, keyed by what they depend on (the backbone's ``frozen_key``, the mask source's
    ``cache_key``, the images). The frozen outputs come from one pass over the images; masks are computed from
    the cached outputs where the mask source reads nothing else (else in the same pass, from the images)."""
    size, cache_dir = settings.image_size, settings.cache_dir
    backbone_key = backbone.frozen_key()
    data_key = _data_key(places, size, settings.resize)
    sides: dict[str, Side] = {"db": (places.db_paths, places.db_labels), "q": (places.q_paths, places.q_labels)}
    last = _last_level(backbone)
    kinds: dict[str, _Kind] = {}
    if settings.storage != "stream":
        kinds["trunk"] = _Kind(
            "trunk", {"backbone": backbone_key, "data": data_key}, trunk_shape(backbone, size), np.uint16, last
        )
        for level in sorted(set(skip_levels) - {last}):
            key = {"backbone": backbone_key, "data": data_key, "level": level}
            kinds[f"skips{level}"] = _Kind("skips", key, skip_shape(backbone, size, level), np.uint16, level)
    if masks is not None:
        channels = 1 if masks.weighting == "binary" else NUM_CLASSES
        grid = grid_size(backbone, size)
        # The grid too: a source that reads the images (the teacher) gives one mask per trunk stride.
        key = {"mask": masks.source.cache_key(size), "weighting": masks.weighting, "data": data_key, "grid": list(grid)}
        kinds["masks"] = _Kind("masks", key, (channels, *grid), np.float16)
    missing = [k for k, kind in kinds.items() if not artifact_dir(cache_dir, kind.kind, kind.key).is_dir()]
    held = {kind.level for kind in kinds.values() if kind.level is not None}
    from_cache = (
        "masks" in missing
        and masks is not None
        and not masks.source.reads_pixels(size)
        and set(masks.source.trunk_levels(size)) <= held
    )
    frozen = [k for k in missing if k != "masks"] if from_cache else missing
    if frozen:
        _build(frozen, kinds, sides, backbone, settings, places.name, masks if "masks" in frozen else None)
    stores = _stores(kinds, sides, settings, last, with_masks=not from_cache)
    if from_cache:
        assert masks is not None
        kind = kinds["masks"]

        def compute(tmp: Path) -> None:
            for side, (paths, labels) in sides.items():
                out = open_array(
                    tmp / f"{side}.npy", kind.dtype, (len(paths), *kind.shape), f"the masks of {places.name}"
                )
                _masks_from_cache(
                    backbone, masks, stores[side], labels, out, settings.batch_size, f"{places.name} {side} masks"
                )
                out.flush()

        folder = build_once(cache_dir, kind.kind, kind.key, compute)
        for side, (paths, _) in sides.items():
            arr = _open(folder / f"{side}.npy", (len(paths), *kind.shape), kind.dtype, folder)
            stores[side].mask = torch.from_numpy(arr)
    return PlaceFeatures(places, stores["db"], stores["q"])


def _stores(
    kinds: dict[str, _Kind], sides: dict[str, Side], settings: StoreSettings, last: int, with_masks: bool
) -> dict[str, FeatureStore]:
    """The stores of both sides from the built caches (trunk in RAM or memory-mapped, skips memory-mapped)."""
    stores, cache_dir = {}, settings.cache_dir
    for side, (paths, _) in sides.items():
        arrays = {
            name: _open(
                artifact_dir(cache_dir, kind.kind, kind.key) / f"{side}.npy",
                (len(paths), *kind.shape),
                kind.dtype,
                artifact_dir(cache_dir, kind.kind, kind.key),
            )
            for name, kind in kinds.items()
            if with_masks or name != "masks"
        }
        trunk = None
        if "trunk" in arrays:
            held = np.array(arrays["trunk"]) if settings.storage == "ram" else arrays["trunk"]
            trunk = torch.from_numpy(held).view(torch.bfloat16)
        skips = {
            kinds[name].level: torch.from_numpy(arr).view(torch.bfloat16)
            for name, arr in arrays.items()
            if name.startswith("skips")
        }
        mask = torch.from_numpy(arrays["masks"]) if "masks" in arrays else None
        stores[side] = FeatureStore(tuple(paths), settings.image_size, trunk, mask, skips, last, settings.resize)
    return stores


def _build(
    missing: list[str],
    kinds: dict[str, _Kind],
    sides: dict[str, Side],
    backbone: nn.Module,
    settings: StoreSettings,
    name: str,
    masks: MaskPass | None,
) -> None:
    """Build the missing caches in one pass per side; each lands under its final name only when whole."""

    def compute(dirs: dict[str, Path]) -> None:
        for side, (paths, labels) in sides.items():
            outs = {
                k: open_array(
                    d / f"{side}.npy",
                    kinds[k].dtype,
                    (len(paths), *kinds[k].shape),
                    f"the {kinds[k].kind} cache of {name}",
                )
                for k, d in dirs.items()
            }
            levels = {kinds[k].level: arr for k, arr in outs.items() if kinds[k].level is not None}
            _extract(
                backbone,
                (paths, labels),
                settings,
                levels,
                masks if "masks" in outs else None,
                outs.get("masks"),
                f"{name} {side}",
            )
            for arr in outs.values():
                arr.flush()

    # The first kind's build computes the others in the same pass into a scratch dir; theirs then
    # only move the files in (or compute alone if a parallel job built the first kind meanwhile).
    cache_dir = settings.cache_dir
    cache_dir.mkdir(parents=True, exist_ok=True)
    scratch = temp_dir(cache_dir, "features")
    try:
        first, *rest = missing
        for k in rest:
            (scratch / k).mkdir()
        build_once(
            cache_dir,
            kinds[first].kind,
            kinds[first].key,
            lambda tmp: compute({first: tmp, **{k: scratch / k for k in rest}}),
        )
        for k in rest:

            def adopt(tmp: Path, k: str = k) -> None:
                if all((scratch / k / f"{side}.npy").is_file() for side in sides):
                    for side in sides:
                        shutil.move(scratch / k / f"{side}.npy", tmp / f"{side}.npy")
                else:
                    compute({k: tmp})

            build_once(cache_dir, kinds[k].kind, kinds[k].key, adopt)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
