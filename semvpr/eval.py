"""Evaluate a checkpoint on any place set: ``python -m semvpr.eval ckpt=PATH [data=... data.root=...]``.

The model is rebuilt from the checkpoint's record (``semvpr.config.restore``); the data comes from this
invocation. The frozen trunk's outputs and the masks of the images are cached (``retrieval.descriptors``),
so evaluating many checkpoints, or one with several mask sources, passes each image through the trunk
once. ``mask=teacher teacher.checkpoint=DIR`` / ``mask=student student.checkpoint=DIR`` / ``mask=none``
replaces the checkpoint's mask source; ``ckpt=none`` evaluates the config's model with no VPR training
(the off-the-shelf baseline). The positives are the place set's own (``PlaceSet.positives``: its shipped
ground truth, or ``data.eval_radius``). Prints Recall@N over all queries (pytorch-NetVlad, the
benchmark) and, where some query has no positive, over queries with positives (MSLS); the last line is
one JSON object, also written as ``eval.json``. Beside it, ``ranks.npy`` holds each query's first-hit
rank (0-based; k, the number retrieved, when no positive is in the top k; -1 when the query has no
positive), in the set's query order: what paired comparisons of two evaluations of the same queries
resample; ``hits.npz``, each query's hit at N = 1, 5, 10, 20 and the database indices it retrieved
(:func:`query_hits`). ``mask.control``, ``mask.apply`` and ``mask.control_seed`` control the mask
(``retrieval.controls``): the invocation's where given, else the checkpoint's. With ``-m`` over several
datasets (``data=a,b``, ``data.root=A,B``), mask sources or controls, a job's bad input fails its own row
only, and ``semvpr.evaltable`` writes one table for the sweep.
"""

from __future__ import annotations

import functools
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, open_dict

from semvpr.config.build import build_places, feature_storage
from semvpr.config.checks import check_config, check_overrides_or_exit
from semvpr.config.command import hydra_command, model_arithmetic, model_pass
from semvpr.config.plan import data_settings, settings_of
from semvpr.config.restore import explicit_keys, is_untrained, load_retriever, with_place_set
from semvpr.config.schema import EvalPca, typed
from semvpr.core.device import resolve
from semvpr.core.errors import SemvprError, one_line
from semvpr.core.io import write_json, write_npy, write_npz
from semvpr.core.logs import say
from semvpr.core.precision import autocast, fp32
from semvpr.core.stops import Interrupted, received_stop, run_stoppable, sweep_stopped_line
from semvpr.data.images import load_image
from semvpr.data.places import PlaceSet
from semvpr.models.whitening import PCAWhitening
from semvpr.reporting.benchmarks_table import HITS_FILE, RANKS_FILE, write_table
from semvpr.reporting.exports import SaveSpec, write_exports
from semvpr.reporting.prediction_images import MaskOf
from semvpr.retrieval.descriptors import place_descriptors
from semvpr.retrieval.features import grid_size
from semvpr.retrieval.recall import RECALL_NS, evaluate, first_hit_ranks
from semvpr.retrieval.retriever import Retriever


def describe(
    retriever: Retriever, cfg: DictConfig, places: PlaceSet, sides: tuple[str, ...] = ("db", "q")
) -> tuple[np.ndarray, ...]:
    """The descriptors of ``places``' database and queries (``sides``; ``retrieval.descriptors``: from the cached
    trunk outputs and masks, memory-mapped, or from the images where ``features.storage`` and the set's size say
    stream), under the mask control of ``cfg.mask`` (``retrieval.controls``)."""
    settings = settings_of(cfg)
    storage = feature_storage(settings, retriever.backbone, {"set": places})
    size, cache, control = settings.data.image_size, settings.storage.cache_dir, settings.masks.control
    resize = settings.data.resize
    return tuple(place_descriptors(retriever, places, side, size, cache, storage, control, resize) for side in sides)


def pca_settings(cfg: DictConfig, retriever: Retriever, merged: DictConfig) -> EvalPca | None:
    """``pca`` as a PCA-whitening to fit here (None without ``pca.dim``), refused in one line before any pass where
    it cannot be: a model whitened already, a dimension above its descriptors'."""
    pca = typed(EvalPca, cfg.get("pca") or {"data": "synthcity"}, "pca")
    if pca.dim is None:
        return None
    if retriever.whitening is not None:
        raise SemvprError(
            f"pca.dim={pca.dim}: {cfg.ckpt} has its own PCA-whitening (model.pca_dim={merged.model.pca_dim}), "
            "fitted after its training; drop pca.dim, or give a checkpoint trained with model.pca_dim=null"
        )
    if pca.dim > retriever.aggregator.output_dim:
        raise SemvprError(
            f"pca.dim={pca.dim}: the model's descriptors have {retriever.aggregator.output_dim} dims; PCA keeps at "
            "most that many"
        )
    return pca


def pca_fit_set(cfg: DictConfig, pca: EvalPca, merged: DictConfig, evaluated: PlaceSet) -> tuple[DictConfig, PlaceSet]:
    """The config and the training split of the place set ``pca.data`` names (the benchmark's
    ``--pca_dataset_folder``), at the evaluated set's image size and resize; refused in one line where it has no
    training split or shares an image with the evaluated set."""
    fit_cfg = merged.copy()
    with open_dict(fit_cfg):
        fit_cfg.data = with_place_set(pca, "pca").data
        fit_cfg.data.image_size = merged.data.image_size
        if "resize" in merged.data:
            fit_cfg.data.resize = merged.data.resize
    if fit_cfg.data.get("train") is None:
        raise SemvprError(
            f"pca.data={pca.data} has no train split to fit a PCA-whitening on; name a place set with one "
            "(synthcity, or folder / pitts30k / msls with pca.root=DIR)"
        )
    train = build_places(data_settings(fit_cfg), ("train",))["train"]
    seen = {p.resolve() for p in (*evaluated.db_paths, *evaluated.q_paths)}
    shared = [p for p in train.db_paths if p.resolve() in seen]
    if shared:
        raise SemvprError(
            f"pca.data={pca.data}: {len(shared)} of its training images are evaluated here (e.g. {shared[0]}); "
            "a PCA fitted on the evaluated set sees its test images: name another pca.data"
        )
    return fit_cfg, train


def fitted_pca(
    dim: int, retriever: Retriever, fit_cfg: DictConfig, train: PlaceSet
) -> tuple[PCAWhitening, dict[str, Any]]:
    """The ``dim``-D PCA-whitening ``pca.dim`` asks for, fitted on the model's descriptors of ``train``'s database
    images (:func:`pca_fit_set`), described as the evaluated database is (the mask and its control too), and what it was
    fitted on."""
    (db,) = describe(retriever, fit_cfg, train, ("db",))
    say(f"PCA-whitening to {dim} dims: fitted on {train.name}'s {len(db)} training database images")
    whitening = PCAWhitening(retriever.aggregator.output_dim, dim).fit(db)
    return whitening, {"dim": dim, "set": train.name, "images": len(db)}


def whitened(whitening: PCAWhitening, descriptors: np.ndarray, device_type: str) -> np.ndarray:
    """``descriptors`` through a fitted PCA-whitening, in fp32 whatever the job's precision, a chunk of rows at a
    time (a memory-mapped set is never held whole twice)."""
    out = np.empty((len(descriptors), whitening.out_dim), np.float32)
    with fp32(device_type):
        for start in range(0, len(descriptors), 65536):
            rows = np.array(descriptors[start : start + 65536], dtype=np.float32)
            out[start : start + len(rows)] = whitening(torch.from_numpy(rows)).numpy()
    return out


def evaluate_checkpoint(
    cfg: DictConfig, explicit: set[str] = frozenset(), run_dir: Path | None = None
) -> dict[str, Any]:
    """Recall@1/5/10/20 of the checkpoint on cfg.data's test split, with what the table reports
    beside it: the set, its protocol (``data.benchmark``), counts, descriptor size, wall time; under
    ``ranks`` and ``top`` (not written to eval.json) each query's first-hit rank and the database indices it
    retrieved, nearest first. The descriptors are computed in the model's arithmetic
    (``config.command.model_arithmetic``: an author's release file in fp32 unless ``trainer.precision`` is
    given), recorded as ``precision``."""
    start = time.perf_counter()
    check_config(cfg, run_dir)
    save = typed(SaveSpec, cfg.get("save") or {}, "save")  # before any pass: a bad value, or h5py missing, is one line
    # The data is the invocation's whatever the model; read after the checkpoint is validated.
    test_set = functools.cache(lambda: build_places(data_settings(cfg), ("test",))["test"])
    device = resolve(cfg.get("device"))
    retriever, merged = load_retriever(
        cfg, explicit, evaluated=lambda: (*test_set().db_paths, *test_set().q_paths), device=device
    )
    test = test_set()
    test.identity("db"), test.identity("q")  # every listed file is checked before the first pass
    asked = pca_settings(cfg, retriever, merged)  # a PCA that cannot be fitted is refused before any pass
    fit_set = pca_fit_set(cfg, asked, merged, test) if asked is not None else None
    with model_arithmetic(cfg, merged, explicit).run(device.type) as precision:
        db, q = describe(retriever, merged, test)
        pca = fitted_pca(asked.dim, retriever, *fit_set) if asked is not None and asked.dim and fit_set else None
    if pca is not None:
        db, q = whitened(pca[0], db, device.type), whitened(pca[0], q, device.type)
    result = evaluate(db, q, test.positives())
    source = retriever.mask_source
    has_segmenter = source is not None and source.segmenter is not None
    segmenter_dir = merged[source.needs].get("checkpoint") if has_segmenter else None
    out = {
        "status": "ok",
        "checkpoint": "none" if is_untrained(cfg.ckpt) else str(cfg.ckpt),
        "data": merged.data.name,
        "set": test.name,
        "benchmark": merged.data.get("benchmark"),
        "aggregator": merged.aggregator.name,
        "mask": merged.mask.name,
        # The directory (or Hub id) the mask's segmenter was read from; null: the checkpoint's own weights.
        "mask_checkpoint": str(segmenter_dir) if segmenter_dir else None,
        # The mask's control (retrieval.controls): none and both for the source's own mask on every image.
        "mask_control": str(merged.mask.control),
        "mask_apply": str(merged.mask.apply),
        "mask_control_seed": int(merged.mask.control_seed),
        "backbone": merged.backbone.name,
        "model": f"{merged.backbone.name}-{type(retriever.aggregator).__name__.lower()}",
        # An author's release file: its name in tables, e.g. "mixvpr (ResNet50, released)".
        **({"release": str(merged.release)} if merged.get("release") else {}),
        "image_size": list(merged.data.image_size),
        "database": len(test.db_paths),
        "queries": len(test.q_paths),
        "descriptor_dim": int(db.shape[1]),
        # A PCA-whitening fitted here (pca.dim): its size and the training database it was fitted on.
        "pca": pca[1] if pca is not None else None,
        "precision": precision,
        "queries_without_positives": result["num_without_positives"],
        **{f"test/R@{n}": round(v, 2) for n, v in result["recalls"].items()},
    }
    if result["num_without_positives"]:
        out.update({f"test/R@{n}_pos": round(v, 2) for n, v in result["recalls_pos"].items()})
    out["wall_s"] = round(time.perf_counter() - start, 1)
    out["ranks"] = first_hit_ranks(result["predictions"], test.positives())
    out["top"] = result["predictions"]
    if run_dir is not None and save.any:  # the files for other tools it was asked for (save.*), beside eval.json
        masks = image_masks(retriever, merged, test) if save.images else None
        size = merged.data.image_size
        out["exported"] = write_exports(save, run_dir, test, db, q, out["top"], test.positives(), size, masks)
    return out


def image_masks(retriever: Retriever, merged: DictConfig, places: PlaceSet) -> MaskOf | None:
    """The weight map each drawn image's features are weighted by (its mask source's own mask, through the learned
    class weights where the model has them), for ``save.images``; None without a mask source, or where a mask
    control replaces the source's masks."""
    source = retriever.mask_source
    if source is None or str(merged.mask.control) != "none":
        return None
    size, resize = tuple(int(v) for v in merged.data.image_size), str(merged.data.get("resize", "bilinear"))
    keep = bool(source.trunk_levels(size))

    @torch.no_grad()
    def mask_of(side: str, i: int) -> np.ndarray:
        paths, labels = (places.db_paths, places.db_labels) if side == "db" else (places.q_paths, places.q_labels)
        image = load_image(paths[i], size, resize)[None].to(retriever.device)
        with autocast(retriever.device):
            outs = retriever.backbone.forward_frozen(image.contiguous(memory_format=torch.channels_last), keep)
            grid = grid_size(retriever.backbone, size)
            mask = source.grid_mask(image, outs, None if labels is None else [labels[i]], grid, retriever.weighting)
            if retriever.class_weights is not None:
                mask = retriever.class_weights(mask)
        return mask[0, 0].float().cpu().numpy()

    return mask_of


def query_hits(ranks: np.ndarray, top: np.ndarray) -> dict[str, np.ndarray]:
    """What ``hits.npz`` holds: ``ns`` (the cut-offs N), ``hits`` (queries × N, bool: a positive among the first
    N retrieved; a query without positives never hits) and ``top`` (queries × k, the retrieved database
    indices, nearest first; k = 20, or the database's size where smaller)."""
    ns = np.asarray(RECALL_NS, dtype=np.int32)
    # A rank of k is a miss (k retrieved, none a positive): beyond k, the first k are all there is.
    retrieved = np.minimum(ns, np.asarray(top).shape[1])
    hits = (ranks[:, None] >= 0) & (ranks[:, None] < retrieved[None, :])
    return {"ns": ns, "hits": hits, "top": np.asarray(top, dtype=np.int32)}


@hydra_command("eval", "eval.json")
def _hydra_main(cfg: DictConfig, out_dir: Path) -> None:
    try:
        with model_pass(cfg) as threads:
            result = {**evaluate_checkpoint(cfg, explicit_keys(), out_dir), "threads": threads.record()}
    except Exception as err:  # noqa: BLE001 - in a sweep every failure becomes its job's row
        if HydraConfig.get().mode != RunMode.MULTIRUN or received_stop() is not None:
            raise  # a stop that surfaced as a library's error is the stop (hydra_command), not a failure
        # In a sweep one dataset's failure must not stop the others; the table shows its line.
        line = one_line(err) if isinstance(err, SemvprError) else f"{type(err).__name__}: {one_line(err)}"
        write_json(out_dir / "eval.json", {"status": "failed", "error": line})
        print(f"semvpr: job failed ({out_dir}): {line}", file=sys.stderr)
        return
    # ranks.npy and hits.npz first: an eval.json beside them says all are complete.
    ranks = np.asarray(result.pop("ranks"), dtype=np.int32)
    exported = result.pop("exported", [])
    write_npy(out_dir / RANKS_FILE, ranks)
    write_npz(out_dir / HITS_FILE, query_hits(ranks, result.pop("top")))
    result["files"] = [RANKS_FILE, HITS_FILE, *exported]  # what the job wrote beside eval.json
    write_json(out_dir / "eval.json", result)
    for n in RECALL_NS:
        pos = f"   ({result[f'test/R@{n}_pos']:.2f} of queries with positives)" if f"test/R@{n}_pos" in result else ""
        print(f"R@{n:<2d} {result[f'test/R@{n}']:6.2f}{pos}")
    print(json.dumps({"run_dir": str(out_dir), **result}))  # last, as train's: where the job's files are


def main() -> None:
    """Console entry point."""
    check_overrides_or_exit(sys.argv[1:], "eval")
    run_stoppable(_hydra_main, sys.argv[1:], _stopped_line)


def _stopped_line(stop: Interrupted) -> str:
    """A stopped evaluation's line; a stopped sweep's names its table, written now."""
    return sweep_stopped_line(stop, write_table) if stop.sweep_dir is not None else f"semvpr: error: {stop}"


if __name__ == "__main__":
    main()
