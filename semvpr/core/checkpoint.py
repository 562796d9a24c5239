"""A checkpoint is data: reading one weights-only, its model record, and writing one safely.

Researchers exchange checkpoints, so nothing read from one is ever run. ``torch.load`` uses
``weights_only=True``, and the model is never rebuilt by instantiating ``_target_``s stored in the
file: a checkpoint records *choices* and plain hyper-parameter values (``config.record`` writes the record
and rebuilds a config from it), which :func:`check_values` checks against the project's own config: known
keys only, the same kind of value, no interpolations, no keys starting with ``_``.

A checkpoint whose model has a mask also records where its segmenter was trained (``segmenter``: a
:class:`~semvpr.core.provenance.TrainedOn`), so that an evaluation on another kind of images can say
so; checkpoints written before that record have none and read as before.

Resuming training reads Lightning's callback state from the checkpoint too: :class:`RunCheckpoint`
drops any path in it that lies outside the run's checkpoint directory, so a tampered or foreign
``last.ckpt`` can never make Lightning read or delete another file. Checkpoints are written by
:class:`RunCheckpointIO`: staged beside their final name (``core.io.atomic_file``), never in ``$TMPDIR``,
so a run killed mid-save leaves nothing outside its run directory.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint

from semvpr.core.errors import SemvprError
from semvpr.core.io import atomic_file, regular_file
from semvpr.core.provenance import TrainedOn

FORMAT = 4
#: Older formats read here: 2 recorded the training protocol in a ``model`` group (``model=netvlad``); 2 and 3
#: recorded a backbone's, an aggregator's and a mask source's constructor values in a ``module`` node of each.
READABLE_FORMATS = (2, 3, FORMAT)

#: What a weights-only read lets a file hold besides tensors and plain containers: numpy scalars (the
#: recall values pytorch-NetVlad's ``checkpoint.pth.tar`` stores beside its weights), rebuilt from bytes.
#: A scalar pickled by numpy 1 names ``numpy.core.multiarray.scalar``, by numpy 2 ``numpy._core...``.
_SAFE_NUMPY = (
    *((np._core.multiarray.scalar, f"{module}.multiarray.scalar") for module in ("numpy.core", "numpy._core")),
    np.dtype,
    *(type(np.dtype(t)) for t in (np.float64, np.float32, np.int64, np.int32, np.bool_)),
)
_UNSUPPORTED = re.compile(r"[Uu]nsupported (?:global: )?GLOBAL (\S+)")
#: The file that marks a folder as a saved segmenter (a student's spec; a teacher's record, or a Hugging Face
#: model's config), and which it is.
SEGMENTER_FILES = {"student.json": "student", "semvpr.json": "teacher", "config.json": "teacher"}


def read_weights(path: str | Path, what: str = "checkpoint") -> Any:
    """A torch file's contents read weights-only (tensors, plain values and numpy scalars; nothing in it
    runs). A file that pickles any other object is refused in one line naming that object."""
    path = Path(path)
    if os.path.lexists(path) and not path.is_dir():
        regular_file(path, what)  # a FIFO or a device is named as what it is, never opened
    if not path.is_file():
        problem = "is a directory, not a file" if path.is_dir() else "not found"
        if what != "checkpoint":
            raise SemvprError(f"{what} {path} {problem}")
        held = [f for f in (path / "checkpoints" / f"{n}.ckpt" for n in ("tested", "last")) if f.is_file()]
        if held:  # a run directory: name the file inside it
            raise SemvprError(f"{what} {path} is a run directory; name a file in it: {' or '.join(map(str, held))}")
        kind = next((kind for name, kind in SEGMENTER_FILES.items() if (path / name).is_file()), None)
        if kind is not None:
            raise SemvprError(
                f"{what} {path} is a saved {kind} (semvpr.segment), not a checkpoint: it masks one, "
                f"ckpt=<checkpoint or none> mask={kind} {kind}.checkpoint={path}"
            )
        raise SemvprError(
            f"{what} {path} {problem} (a run writes <run dir>/checkpoints/tested.ckpt, and last.ckpt to resume)"
        )
    with path.open("rb") as file:
        head = file.read(4)
    if head != b"PK\x03\x04" and head[:1] != b"\x80":
        raise SemvprError(
            f"{path} is not a readable {what}: not a torch file (neither the zip archive torch.save writes "
            "nor a pickle of protocol 2 or later)"
        )
    try:
        with torch.serialization.safe_globals(list(_SAFE_NUMPY)), warnings.catch_warnings():
            # Another pickle protocol than torch's own: read or refused below, not a warning above the line.
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unreadable file gets the same one line
        pickled = _UNSUPPORTED.search(str(err))
        if pickled is not None:
            raise SemvprError(
                f"{what} {path} is refused: it pickles an object ({pickled.group(1)}), and only weights are "
                "read from a file (nothing in it is run)"
            ) from None
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        # The weights-only reader's own reason follows its advice to read the file unsafely, which semvpr never does.
        reason = next(
            (lines[i + 1] for i, line in enumerate(lines[:-1]) if line.endswith("WeightsUnpickler error:")), None
        )
        # Never torch's advice to load the file unsafely (weights_only=False), nor its pointer to its docs.
        plain = [ln for ln in lines if "weights_only" not in ln and not ln.startswith("Check the documentation")]
        detail = f"the weights-only reader cannot read it: {reason}" if reason else (plain or [""])[0]
        raise SemvprError(
            f"{path} is not a readable {what} ({type(err).__name__}{': ' + detail if detail else ''})"
        ) from None


#: Names a wrapper gives the module it wraps, adding no weight: ``nn.DataParallel`` and
#: ``DistributedDataParallel``'s ``module``, ``torch.compile``'s ``_orig_mod``.
WRAPPERS = ("module", "_orig_mod")


#: Where a training checkpoint keeps the model's weights: Lightning and pytorch-NetVlad under ``state_dict``,
#: CosPlace's, EigenPlaces' and gmberton's benchmark's ``last_checkpoint.pth`` under ``model_state_dict``.
STATE_KEYS = ("state_dict", "model_state_dict")


def weights_in(contents: Any, where: str) -> Any:
    """The model weights in a weight file's contents: a training checkpoint's (:data:`STATE_KEYS`) or the
    contents themselves (a plain state dict), wrapper names taken out (:func:`unwrapped`) where it is a dict."""
    if isinstance(contents, dict):
        contents = next((contents[k] for k in STATE_KEYS if isinstance(contents.get(k), dict)), contents)
    return unwrapped(contents, where) if isinstance(contents, dict) else contents


def unwrapped(state: dict[str, Any], where: str) -> dict[str, Any]:
    """``state`` with the wrappers' names (:data:`WRAPPERS`) taken out of its keys at the top (a whole model
    saved through a wrapper: ``module.backbone.0.weight``) and one level down (wrapped parts, as pytorch-NetVlad's
    multi-GPU ``encoder.module.0.weight``, ``pool.module.centroids``); other keys as they are. Two keys that
    would then name one weight are refused in one line."""
    out: dict[str, Any] = {}
    given: dict[Any, Any] = {}  # each name's key in the file
    for key, value in state.items():
        name = _unwrapped_key(key) if isinstance(key, str) else key
        if name in given:
            raise SemvprError(f"{where}: two keys name the weight {name!r}: {given[name]!r} and {key!r}")
        given[name], out[name] = key, value
    return out


def _unwrapped_key(key: str) -> str:
    """``key`` without a wrapper's names at the top and one level down."""
    parts = key.split(".")
    for depth in (0, 1):
        while len(parts) > depth + 1 and parts[depth] in WRAPPERS:
            del parts[depth]
    return ".".join(parts)


def is_semvpr_checkpoint(contents: Any) -> bool:
    """Whether a file's contents carry a semvpr model record (of any format)."""
    record = contents.get("hyper_parameters") if isinstance(contents, dict) else None
    return isinstance(record, dict) and ("format" in record or "config" in record)


def weight_fault(key: Any, value: Any) -> str | None:
    """Why a state dict's entry is no model weight (None when it is one): a key that is no string, a value that
    is not a tensor, complex, a view claiming more numbers than the file stores (strides of 0: checking or
    copying it would fill the memory), or not finite."""
    if not isinstance(key, str):
        return "is not named by a string"
    if not isinstance(value, torch.Tensor):
        return f"is not a tensor ({type(value).__name__})"
    if value.is_complex():
        return f"is complex ({value.dtype})"
    stored = value.untyped_storage().nbytes() // value.element_size()
    if value.numel() > stored:
        return f"has shape {tuple(value.shape)} ({value.numel():,} values) from {stored:,} stored"
    if value.is_floating_point() and not torch.isfinite(value).all():
        return "is not finite"
    return None


def dtype_fault(value: torch.Tensor, needed: torch.Tensor) -> str | None:
    """Why a file's weight ``value`` cannot take the place of the model's ``needed`` in the dtype the model
    holds it in (None when it can): integers or booleans where the model holds floats (a cast would make
    weights of them without a word), or values beyond the largest finite number of that dtype (finite in the
    file, infinite once cast)."""
    if not needed.is_floating_point():
        return None
    held, given = (str(t.dtype).removeprefix("torch.") for t in (needed, value))
    if not value.is_floating_point():
        return f"is {given}, where the model holds {held} weights"
    largest = float(value.detach().abs().max()) if value.numel() else 0.0
    if largest > torch.finfo(needed.dtype).max:
        return f"holds {largest:.3g}, beyond {held}'s range"
    return None


def read_checkpoint(path: str | Path, contents: Any = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The state dict and the model record of a semvpr checkpoint (weights-only load; ``contents``: the
    file's, where already read)."""
    path = Path(path)
    ckpt = read_weights(path) if contents is None else contents
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        raise SemvprError(f"{path} is not a semvpr checkpoint (no state_dict)")
    for key, value in ckpt["state_dict"].items():
        fault = weight_fault(key, value)
        if fault is not None:
            raise SemvprError(f"{path}: weight {key!r} {fault}; the checkpoint is damaged")
    record = ckpt.get("hyper_parameters")
    if not isinstance(record, dict) or record.get("format") not in READABLE_FORMATS:
        if isinstance(record, dict) and "config" in record and "format" not in record:
            raise SemvprError(
                f"{path} was written by an older semvpr (checkpoint format 1: it stores Hydra "
                "_target_s, and its VGG16 features were cut after conv5_3's ReLU); it cannot be "
                "loaded safely or faithfully: retrain it with this version"
            )
        raise SemvprError(f"{path} is not a semvpr checkpoint of format {FORMAT} (no model record)")
    return ckpt["state_dict"], record


def segmenter_of(record: dict[str, Any], where: str = "checkpoint") -> TrainedOn | None:
    """The data the checkpoint's mask segmenter was trained on; None where the record does not say."""
    if "segmenter" not in record:
        return None
    return TrainedOn.from_value(record["segmenter"], f"{where}: segmenter")


def check_values(stored: Any, schema: Any, path: str, *, source: str, project_values: Any = None) -> None:
    """Refuse a stored value (a checkpoint's record, a resumed run's config) that the project's config
    could not have produced: only keys of ``schema`` (an empty mapping there takes keys of the user's
    own: ``data.render: {}``), values of the same kind, no ``_`` keys and no ``${...}``, unless
    ``project_values`` (the project's config at the same place, unresolved) holds exactly the same
    entry: a resumed run's record carries the ``_target_``s and interpolations of the files it was
    composed from, which add nothing. ``source`` names what was read, for the one-line refusal; ``path``
    prefixes every key named (a path ending in ": " is a heading, not a key)."""
    if isinstance(stored, dict):
        if not isinstance(schema, dict):
            raise SemvprError(f"{path} is a mapping where the project's config has {schema!r}")
        project = project_values if isinstance(project_values, dict) else {}
        for key, value in stored.items():
            if isinstance(key, str) and key in project and project[key] == value and _project_only(key, value):
                continue  # the project's own _target_ / interpolation, unchanged
            if not isinstance(key, str) or key.startswith("_"):
                raise SemvprError(
                    f"{_join(path, key)} is refused: keys such as _target_ are never read from {source} "
                    "(the project's config files supply them)"
                )
            if key not in schema:
                if schema:
                    raise SemvprError(f"{_join(path, key)} is not a key of the project's config")
                if isinstance(value, (dict, list)):
                    raise SemvprError(f"{_join(path, key)} is not a plain value")
                check_values(value, None, f"{_join(path, key)}", source=source)
                continue
            check_values(value, schema[key], f"{_join(path, key)}", source=source, project_values=project.get(key))
    elif isinstance(stored, list):
        if schema is not None and not isinstance(schema, list):
            raise SemvprError(f"{path} is a list where the project's config has {schema!r}")
        for i, value in enumerate(stored):
            if isinstance(value, (dict, list)):
                raise SemvprError(f"{path}[{i}] is not a plain value")
            check_values(value, None, f"{path}[{i}]", source=source)
    else:
        if isinstance(stored, str) and "${" in stored:
            raise SemvprError(f"{path}={stored!r} is refused: interpolations are never read from {source}")
        derived = isinstance(project_values, str) and "${" in project_values
        if not derived and not _same_kind(stored, schema):
            raise SemvprError(f"{path}={stored!r} has the wrong type (the project's config has {schema!r})")


def _join(path: str, key: object) -> str:
    """``path.key``, or ``path key`` after a heading (``"resuming <run>: "``)."""
    return f"{path}{key}" if path.endswith(": ") else f"{path}.{key}"


def _project_only(key: str, value: Any) -> bool:
    """Whether an entry is one only the project's files may supply (a ``_`` key, or text with ``${``)."""
    if key.startswith("_"):
        return True
    if isinstance(value, str):
        return "${" in value
    if isinstance(value, dict):
        return any(_project_only(str(k), v) for k, v in value.items())
    if isinstance(value, list):
        return any(isinstance(v, str) and "${" in v for v in value)
    return False


def _same_kind(value: Any, schema: Any) -> bool:
    """Whether a plain stored value may replace the config's value (null accepts any plain value)."""
    if value is not None and not isinstance(value, (bool, int, float, str)):
        return False
    if schema is None or value is None:
        return True
    if schema == "auto":  # a setting the project leaves to semvpr (threads, device) takes a number or a word
        return isinstance(value, (int, str)) and not isinstance(value, bool)
    if isinstance(schema, bool) or isinstance(value, bool):
        return isinstance(schema, bool) and isinstance(value, bool)
    if isinstance(schema, float):
        return isinstance(value, (int, float))
    return type(value) is type(schema)


class RunCheckpoint(ModelCheckpoint):
    """Lightning's ModelCheckpoint, restoring from a checkpoint only paths inside its own ``dirpath``.

    On resume Lightning restores ``best_model_path`` etc. from the file and later deletes or loads
    those files; a path elsewhere (a tampered ``last.ckpt``, another run's checkpoint) is dropped
    here, with the score that went with it. A run directory that was moved (copied off a cluster's
    scratch disk, renamed) resumes from its own ``last.ckpt`` as it would have in place: the files the
    state names in the directory it was written in are read in this one (Lightning itself keeps only
    the old ``best_model_path`` then, so the resumed run forgot its best score and tested the last
    epoch's weights as the best).
    """

    _trainer: L.Trainer | None = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        super().setup(trainer, pl_module, stage)
        self._trainer = trainer  # its ckpt_path names the file being resumed when the state is loaded

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        resumed = self._trainer.ckpt_path if self._trainer is not None else None
        own = Path(self.dirpath or ".")
        moved = resumed is not None and Path(resumed).resolve().parent == own.resolve()
        super().load_state_dict(confine_callback_state(state_dict, own, own_file=moved))


def confine_callback_state(state: dict[str, Any], dirpath: Path, own_file: bool = False) -> dict[str, Any]:
    """ModelCheckpoint state with every file outside ``dirpath`` forgotten. ``own_file``: the state was
    read from a file in ``dirpath``, so the files it names in the directory it was written in (the same
    run's, before the directory moved) are taken from ``dirpath`` where they are there."""
    root = dirpath.resolve()
    state = dict(state)
    written_in = state.get("dirpath")
    if own_file and isinstance(written_in, str) and Path(written_in) != dirpath:

        def moved(value: Any) -> Any:
            if isinstance(value, str) and value and Path(value).parent == Path(written_in):
                here = dirpath / Path(value).name
                return str(here) if here.is_file() else value
            return value

        for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
            state[key] = moved(state.get(key))
        if isinstance(state.get("best_k_models"), dict):
            state["best_k_models"] = {moved(k): v for k, v in state["best_k_models"].items()}
        state["dirpath"] = str(dirpath)

    def inside(value: Any) -> bool:
        return isinstance(value, str) and bool(value) and Path(value).resolve().is_relative_to(root)

    for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
        if key in state and not inside(state[key]):
            state[key] = ""
    if not state.get("best_model_path"):
        state["best_model_score"] = None
    if isinstance(state.get("best_k_models"), dict):
        state["best_k_models"] = {k: v for k, v in state["best_k_models"].items() if inside(k)}
    return state


class RunCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer, staging each file beside its target (``core.io.atomic_file``: a fresh
    hidden name in the same folder, renamed when complete) where Lightning's own stages it in ``$TMPDIR``
    (fsspec's transaction), outside the run directory."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__}.save_checkpoint takes no storage_options, got {storage_options!r}")
        with atomic_file(Path(path)) as handle:
            torch.save(checkpoint, handle)
