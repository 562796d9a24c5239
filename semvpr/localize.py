"""Localise query images: ``python -m semvpr.localize ckpt=PATH queries=DIR [data=...] [top_k=5]``.

Each image in DIR is described with the checkpoint's full pipeline (backbone, mask, aggregator)
and matched against the database of ``data``'s test split (its descriptors cached as in
``semvpr.eval``). The model is the one ``semvpr.eval`` evaluates: a checkpoint (its mask source
replaceable with ``mask=``), or ``ckpt=none``. Prints, per query, the best database image with its
position (UTM metres, or the frame of a frame-aligned set) and descriptor distance; writes the top-k of each
to ``localize.json`` in the run directory. Where a query's name gives where it was taken (``@east@north@...``, as
VPR-datasets-downloader names images) and the database has UTM positions, each match also has how far it is
(``metres``) and whether it is right (``correct``: within ``data.eval_radius``, else 25 m); ``save.images=N``
draws N queries with their matches (``predictions/<query index>.jpg``, as ``semvpr.eval`` does). Images pass through
the model in eval's arithmetic (an author's release file in fp32 unless ``trainer.precision`` is given:
``config.command.model_arithmetic``).
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from semvpr.config.build import build_places, feature_storage
from semvpr.config.checks import check_config, check_overrides_or_exit
from semvpr.config.command import hydra_command, model_arithmetic, model_pass
from semvpr.config.plan import data_settings, settings_of
from semvpr.config.restore import explicit_keys, load_retriever
from semvpr.config.schema import typed
from semvpr.core.device import resolve
from semvpr.core.errors import SemvprError
from semvpr.core.io import write_json
from semvpr.core.stops import run_stoppable
from semvpr.data.places import PlaceSet, folder_images, parse_utm_name
from semvpr.reporting.exports import SaveSpec
from semvpr.reporting.prediction_images import drawn_queries, query_row, save_row
from semvpr.retrieval.descriptors import place_descriptors
from semvpr.retrieval.recall import check_finite, knn

#: The radius a match counts as right within, for a set without its own (``data.eval_radius``): the benchmarks' 25 m.
DEFAULT_RADIUS = 25.0

#: Settings of semvpr.eval's (its config is localize's base) that localize does not read: refused when set.
EVAL_ONLY = ("pca.dim", "save.descriptors", "save.hloc", "save.predictions")


def localize(cfg: DictConfig, explicit: set[str] = frozenset(), run_dir: Path | None = None) -> list[dict[str, Any]]:
    """Top-k database matches (path, position as the set gives one, distance) for every query image."""
    check_config(cfg, run_dir)
    for key in EVAL_ONLY:
        if OmegaConf.select(cfg, key, default=None) not in (None, False):
            raise SemvprError(
                f"{key}={OmegaConf.select(cfg, key)} is semvpr.eval's; localize does not read it: drop it"
            )
    save = typed(SaveSpec, cfg.get("save") or {}, "save")
    paths = folder_images(cfg.queries, "queries")
    # The data is the invocation's whatever the model; read after the checkpoint is validated.
    database = functools.cache(lambda: build_places(data_settings(cfg), ("test",))["test"])
    device = resolve(cfg.get("device"))
    retriever, merged = load_retriever(
        cfg, explicit, new_images=True, evaluated=lambda: (*database().db_paths, *paths), device=device
    )
    places, settings = database(), settings_of(merged)
    size, resize = settings.data.image_size, settings.data.resize
    storage = feature_storage(settings, retriever.backbone, {"test": places})
    q_desc = np.empty((len(paths), retriever.descriptor_dim), np.float32)
    with model_arithmetic(cfg, merged, explicit).run(device.type):
        db_desc = place_descriptors(retriever, places, "db", size, settings.storage.cache_dir, storage, resize=resize)
        retriever.describe_images(paths, None, size, q_desc, desc="queries", resize=resize)
    check_finite(q_desc, f"the query images in {cfg.queries}")
    top = knn(db_desc, q_desc, int(cfg.top_k))
    radius = places.eval_radius if places.eval_radius is not None else DEFAULT_RADIUS
    out = []
    for path, row, desc in zip(paths, top, q_desc):
        dist = np.linalg.norm(db_desc[row] - desc[None], axis=1)
        where = query_utm(path) if places.positions == "utm" else None
        matches = []
        for j, d in zip(row, dist):
            match = {"path": str(places.db_paths[j]), **places.position("db", j), "distance": float(d)}
            if where is not None and "utm" in match:  # the query's own position: the match is right or wrong
                match["metres"] = float(np.hypot(*np.subtract(match["utm"], where)))
                match["correct"] = match["metres"] <= radius
            matches.append(match)
        out.append({"query": str(path), **({"utm": list(where)} if where is not None else {}), "matches": matches})
    if run_dir is not None and save.images:
        draw_matches(run_dir, places, paths, out, top, save, tuple(size))
    return out


def draw_matches(
    run_dir: Path,
    places: PlaceSet,
    paths: list[Path],
    results: list[dict[str, Any]],
    top: np.ndarray,
    save: SaveSpec,
    image_size: tuple[int, int],
) -> None:
    """``save.images`` queries spread over the folder, each drawn with its first ``save.image_top`` matches as
    ``predictions/<query index>.jpg`` (``reporting.prediction_images``): framed right or wrong where the query's
    name gives its position, grey where nothing says; ``save.only_wrong``: of the queries whose first is wrong."""
    wrong = np.array([r["matches"][0].get("correct") is False for r in results], bool)
    for i in drawn_queries(~wrong, save.images, save.only_wrong):
        matches = results[i]["matches"][: save.image_top]
        known = "correct" in matches[0]
        positives = np.array([j for j, m in zip(top[i], matches) if m.get("correct")]) if known else None
        at = {"utm": results[i]["utm"]} if "utm" in results[i] else {}
        distances = [m["distance"] for m in matches]
        row = query_row(places, (paths[i], at), top[i, : len(matches)], distances, positives, image_size)
        save_row(run_dir, int(i), len(paths), row)


def query_utm(path: Path) -> tuple[float, float] | None:
    """A query's position where its name gives one (VPR-datasets-downloader's ``@east@north@...`` names)."""
    try:
        return parse_utm_name(path)
    except SemvprError:
        return None


@hydra_command("localize", "localize.json")
def _hydra_main(cfg: DictConfig, run_dir: Path) -> None:
    with model_pass(cfg):
        results = localize(cfg, explicit_keys(), run_dir)
    output = run_dir / "localize.json"
    write_json(output, results)
    for result in results:
        best = result["matches"][0]
        verdict = {True: ", right", False: ", wrong"}.get(best.get("correct"), "")
        print(
            f"{Path(result['query']).name}: {Path(best['path']).name} ({_where(best)}d={best['distance']:.3f}{verdict})"
        )
    # top_k as returned (at most the database's size); folder_images refuses a folder without images.
    print(json.dumps({"queries": len(results), "top_k": len(results[0]["matches"]), "output": str(output)}))


def _where(match: dict[str, Any]) -> str:
    """A match's position for the summary line, as its place set gives one (UTM metres or a frame)."""
    if "utm" in match:
        return f"E {match['utm'][0]:.1f}, N {match['utm'][1]:.1f}, "
    return f"frame {match['frame']}, " if "frame" in match else ""


def main() -> None:
    """Console entry point."""
    check_overrides_or_exit(sys.argv[1:], "localize")
    run_stoppable(_hydra_main, sys.argv[1:])


if __name__ == "__main__":
    main()
