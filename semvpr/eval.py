"""Evaluate a checkpoint on any place set: ``python -m semvpr.eval ckpt=PATH [data=... data.root=...]``.

The model is rebuilt from the checkpoint's record, validated against the project's own configs
(``semvpr.checkpoint``: nothing stored in the file is ever run), and its weights are loaded; the
data comes from this invocation. Images are streamed through the whole model once; only the
descriptors are cached (memory-mapped, kind ``descriptors``), so memory does not grow with the
dataset. The positives are the place set's own (``PlaceSet.positives``: its shipped ground truth,
or ``data.eval_radius``). Prints Recall@N over all queries (pytorch-NetVlad, the benchmark) and,
where some query has no positive, over queries with positives (MSLS); the last line is one JSON
object, also written as ``eval.json``. With ``-m`` over several datasets (``data=a,b``,
``data.root=A,B``), a job's bad input fails its own row only, and ``semvpr.evaltable`` writes one
table for the sweep.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from semvpr.artifacts import build_once, state_hash
from semvpr.build import (build_aggregator, build_backbone, build_class_weights, build_mask_source, build_places,
                          check_config)
from semvpr.checkpoint import model_config, read_checkpoint
from semvpr.data.places import PlaceSet
from semvpr.errors import SemvprError, exit_on_user_error, one_line
from semvpr.io import CONF_DIR, open_array, write_json
from semvpr.metrics import RECALL_NS
from semvpr.models.netvlad import PCAWhitening
from semvpr.models.retriever import Retriever, evaluate
from semvpr.logs import quiet_third_party


#: Command-line group choices that would change the model, and the groups each one sets.
MODEL_OVERRIDES = {"backbone": ("backbone",), "aggregator": ("aggregator",), "mask": ("mask",),
                   "filter": ("aggregator", "mask")}


def load_retriever(cfg: DictConfig, explicit: set[str] = frozenset()) -> tuple[Retriever, DictConfig]:
    """The checkpoint ``cfg.ckpt`` as a retriever in eval mode, and the config it was rebuilt with."""
    state, record = read_checkpoint(cfg.ckpt)
    merged = model_config(record, cfg, where=f"checkpoint {cfg.ckpt}")
    trained = f"backbone={merged.backbone.name} aggregator={merged.aggregator.name} mask={merged.mask.name}"
    for override in sorted(explicit & set(MODEL_OVERRIDES)):
        if any(cfg[group].name != merged[group].name for group in MODEL_OVERRIDES[override]):
            raise SemvprError(f"checkpoint {cfg.ckpt} was trained with {trained}; drop the {override}= override "
                              "(the model comes from the checkpoint)")
    backbone = build_backbone(merged, pretrained=False)
    aggregator = build_aggregator(merged, backbone)
    whitening = PCAWhitening(aggregator.output_dim, merged.model.pca_dim) if merged.model.pca_dim else None
    retriever = Retriever(backbone, aggregator, build_mask_source(merged, backbone), whitening,
                          eval_batch_size=merged.model.eval_batch_size, num_workers=merged.data.num_workers,
                          record=record, class_weights=build_class_weights(merged))
    try:
        retriever.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise SemvprError(f"checkpoint {cfg.ckpt} does not fit {trained}: {str(err).splitlines()[0]}") from None
    return retriever.eval(), merged


def descriptor_dim(retriever: Retriever) -> int:
    """Size of the retriever's global descriptor (after PCA-whitening, if any)."""
    return retriever.whitening.out_dim if retriever.whitening is not None else retriever.aggregator.output_dim


def place_descriptors(retriever: Retriever, places: PlaceSet, side: str, cfg: DictConfig) -> np.ndarray:
    """Descriptors of a place set's database or queries (memory-mapped), computed once per model and data."""
    paths, labels = (places.db_paths, places.db_labels) if side == "db" else (places.q_paths, places.q_labels)
    key = {"model": state_hash(retriever.state_dict()), "images": places.identity(side),
           "image_size": list(cfg.data.image_size)}
    dim = descriptor_dim(retriever)

    def build(tmp: Path) -> None:
        out = open_array(tmp / "descriptors.npy", np.float32, (len(paths), dim), f"the descriptors of {places.name}")
        retriever.describe_images(paths, labels, cfg.data.image_size, out, desc=f"{places.name} {side}")
        out.flush()

    folder = build_once(cfg.paths.cache_dir, "descriptors", key, build)
    try:
        desc = np.load(folder / "descriptors.npy", mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as err:
        raise SemvprError(f"descriptor cache {folder} is unreadable ({type(err).__name__}); delete it to rebuild") from None
    if desc.shape != (len(paths), dim) or desc.dtype != np.float32:
        raise SemvprError(f"descriptor cache {folder} holds {desc.dtype}{list(desc.shape)}, expected "
                          f"float32[{len(paths)}, {dim}]; delete it to rebuild")
    return desc


def evaluate_checkpoint(cfg: DictConfig, explicit: set[str] = frozenset()) -> dict[str, Any]:
    """Recall@1/5/10/20 of the checkpoint on cfg.data's test split, with what the table reports
    beside it: the set, its protocol (``data.benchmark``), counts, descriptor size, wall time."""
    start = time.perf_counter()
    check_config(cfg)
    retriever, merged = load_retriever(cfg, explicit)
    test = build_places(merged, ("test",))["test"]
    db = place_descriptors(retriever, test, "db", merged)
    result = evaluate(db, place_descriptors(retriever, test, "q", merged), test.positives())
    out = {"status": "ok", "checkpoint": str(cfg.ckpt), "data": merged.data.name, "set": test.name,
           "benchmark": merged.data.get("benchmark"), "aggregator": merged.aggregator.name, "mask": merged.mask.name,
           "backbone": merged.backbone.name, "model": f"{merged.backbone.name}-{type(retriever.aggregator).__name__.lower()}",
           "database": len(test.db_paths), "queries": len(test.q_paths), "descriptor_dim": int(db.shape[1]),
           "queries_without_positives": result["num_without_positives"],
           **{f"test/R@{n}": round(v, 2) for n, v in result["recalls"].items()}}
    if result["num_without_positives"]:
        out.update({f"test/R@{n}_pos": round(v, 2) for n, v in result["recalls_pos"].items()})
    out["wall_s"] = round(time.perf_counter() - start, 1)
    return out


def explicit_keys() -> set[str]:
    """Config keys this invocation overrode on the command line."""
    return {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}


@hydra.main(config_path=CONF_DIR, config_name="eval", version_base="1.3")
@exit_on_user_error
def _hydra_main(cfg: DictConfig) -> None:
    quiet_third_party()
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        result = evaluate_checkpoint(cfg, explicit_keys())
    except SemvprError as err:
        if HydraConfig.get().mode != RunMode.MULTIRUN:
            raise
        # In a sweep one dataset's bad input must not stop the others; the table shows the line.
        write_json(out_dir / "eval.json", {"status": "failed", "error": one_line(err)})
        print(f"semvpr: job failed ({out_dir}): {one_line(err)}", file=sys.stderr)
        return
    write_json(out_dir / "eval.json", result)
    for n in RECALL_NS:
        pos = f"   ({result[f'test/R@{n}_pos']:.2f} of queries with positives)" if f"test/R@{n}_pos" in result else ""
        print(f"R@{n:<2d} {result[f'test/R@{n}']:6.2f}{pos}")
    print(json.dumps(result))


def main() -> None:
    """Console entry point."""
    _hydra_main()


if __name__ == "__main__":
    main()
