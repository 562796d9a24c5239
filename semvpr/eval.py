"""Evaluate a checkpoint on any place set: ``python -m semvpr.eval ckpt=PATH [data=... data.root=...]``.

The model is rebuilt from the checkpoint's record, validated against the project's own configs
(``semvpr.checkpoint``: nothing stored in the file is ever run), and its weights are loaded; the
data comes from this invocation. Images are streamed through the whole model once; only the
descriptors are cached (memory-mapped, kind ``descriptors``), so memory does not grow with the
dataset. Prints Recall@N over all queries (pytorch-NetVlad, the benchmark) and, where some query
has no positive, over queries with positives (MSLS); the last line is one JSON object.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from semvpr.artifacts import build_once, state_hash
from semvpr.build import (build_backbone, build_class_weights, build_mask_source, build_places, check_config,
                          instantiate_node)
from semvpr.checkpoint import model_config, read_checkpoint
from semvpr.data.places import PlaceSet
from semvpr.errors import SemvprError, exit_on_user_error
from semvpr.models.netvlad import PCAWhitening
from semvpr.metrics import RECALL_NS
from semvpr.models.retriever import Retriever, evaluate
from semvpr.io import CONF_DIR, open_array, write_json


def load_retriever(cfg: DictConfig, explicit: set[str] = frozenset()) -> tuple[Retriever, DictConfig]:
    """The checkpoint ``cfg.ckpt`` as a retriever in eval mode, and the config it was rebuilt with."""
    state, record = read_checkpoint(cfg.ckpt)
    merged = model_config(record, cfg, where=f"checkpoint {cfg.ckpt}")
    for group in sorted(explicit & {"backbone", "filter"}):
        if cfg[group].name != merged[group].name:
            raise SemvprError(f"checkpoint {cfg.ckpt} was trained with backbone={merged.backbone.name} "
                              f"filter={merged.filter.name}; drop the {group}= override (the model comes from the checkpoint)")
    backbone = build_backbone(merged, pretrained=False)
    aggregator = instantiate_node(merged.filter.aggregator, dim=backbone.out_channels)
    whitening = PCAWhitening(aggregator.output_dim, merged.model.pca_dim) if merged.model.pca_dim else None
    retriever = Retriever(backbone, aggregator, build_mask_source(merged, backbone), whitening,
                          eval_batch_size=merged.model.eval_batch_size, num_workers=merged.data.num_workers,
                          record=record, class_weights=build_class_weights(merged))
    try:
        retriever.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise SemvprError(f"checkpoint {cfg.ckpt} does not fit backbone={merged.backbone.name} "
                          f"filter={merged.filter.name}: {str(err).splitlines()[0]}") from None
    return retriever.eval(), merged


def place_descriptors(retriever: Retriever, places: PlaceSet, side: str, cfg: DictConfig) -> np.ndarray:
    """Descriptors of a place set's database or queries (memory-mapped), computed once per model and data."""
    paths, labels = (places.db_paths, places.db_labels) if side == "db" else (places.q_paths, places.q_labels)
    key = {"model": state_hash(retriever.state_dict()), "images": places.identity(side),
           "image_size": list(cfg.data.image_size)}
    dim = retriever.whitening.out_dim if retriever.whitening is not None else retriever.aggregator.output_dim

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
    """Recall@1/5/10/20 of the checkpoint on cfg.data's test split."""
    check_config(cfg)
    retriever, merged = load_retriever(cfg, explicit)
    test = build_places(merged, ("test",))["test"]
    result = evaluate(place_descriptors(retriever, test, "db", merged), place_descriptors(retriever, test, "q", merged),
                      test.positives(25.0))
    out = {"checkpoint": str(cfg.ckpt), "data": merged.data.name, "filter": merged.filter.name,
           "backbone": merged.backbone.name, "database": len(test.db_paths), "queries": len(test.q_paths),
           "queries_without_positives": result["num_without_positives"],
           **{f"test/R@{n}": round(v, 2) for n, v in result["recalls"].items()}}
    if result["num_without_positives"]:
        out.update({f"test/R@{n}_pos": round(v, 2) for n, v in result["recalls_pos"].items()})
    return out


def explicit_keys() -> set[str]:
    """Config keys this invocation overrode on the command line."""
    return {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}


@hydra.main(config_path=CONF_DIR, config_name="eval", version_base="1.3")
@exit_on_user_error
def _hydra_main(cfg: DictConfig) -> None:
    result = evaluate_checkpoint(cfg, explicit_keys())
    write_json(Path(HydraConfig.get().runtime.output_dir) / "eval.json", result)
    for n in RECALL_NS:
        pos = f"   ({result[f'test/R@{n}_pos']:.2f} of queries with positives)" if f"test/R@{n}_pos" in result else ""
        print(f"R@{n:<2d} {result[f'test/R@{n}']:6.2f}{pos}")
    print(json.dumps(result))


def main() -> None:
    """Console entry point."""
    _hydra_main()


if __name__ == "__main__":
    main()
