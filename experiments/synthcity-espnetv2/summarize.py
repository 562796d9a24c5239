"""results.csv of the synthcity-espnetv2 runs (run.sh OUT): per SynthCity draw, ESPNetv2's scores on the draw's
segmentation val split and those of the student distilled from its labels of the draw's segmentation train
images (results.json of each ``semvpr.segment`` run; the student's ``train_iou_vs_labels``: its static mask
against ESPNetv2's on those train images), a row per model and draw and each model's mean.

    python experiments/synthcity-espnetv2/summarize.py OUT
"""

from __future__ import annotations

from pathlib import Path

from semvpr.core.errors import SemvprError, exit_on_user_error
from semvpr.core.io import read_json, write_csv
from semvpr.reporting.evaluations import summary_input

DRAWS = (0, 1, 2)
SCORES = ("miou", "dynamic_iou", "nonstatic_iou", "dynamic_removed", "static_removed", "sky_removed")
CLASSES = ("road", "building", "vegetation", "sky", "car", "bus", "person")
FIELDS = ("model", "draw", "images", *SCORES, *(f"iou_{c}" for c in CLASSES), "train_iou_vs_labels")
#: The models of each run: its results.json entry and the row's label.
MODELS = {
    "teacher": "ESPNetv2 s=2.0 (Cityscapes)",
    "student_efficientnet_lite0": "student of ESPNetv2 (its SynthCity labels)",
}


def _scores(entry: dict) -> dict[str, float]:
    """A results.json entry's val scores (a student has no class map: no mIoU, no per-class IoU)."""
    scores = entry["val"]
    values = {k: round(scores[k], 4) for k in SCORES if k in scores}
    values |= {f"iou_{c}": round(scores["class_iou"][c], 4) for c in CLASSES if "class_iou" in scores}
    if "train_iou_vs_labels" in entry:
        values["train_iou_vs_labels"] = round(entry["train_iou_vs_labels"], 4)
    return values


@exit_on_user_error
def main() -> None:
    out = summary_input(__doc__.splitlines()[0], "experiments/synthcity-espnetv2/run.sh")
    results = {draw: read_json(out / f"segment-s{draw}" / "results.json", "a semvpr.segment result") for draw in DRAWS}
    for draw, result in results.items():
        if Path(result["dataset"]["root"]).parent.name != f"synthcity-s{draw}":
            raise SemvprError(f"{out}/segment-s{draw} scored {result['dataset']['root']}, not draw {draw}'s city")
        if missing := [key for key in MODELS if key not in result]:
            raise SemvprError(f"{out}/segment-s{draw}: no {missing[0]} in results.json; rerun run.sh")
    rows = []
    for key, model in MODELS.items():
        drawn = [
            {"model": model, "draw": draw, "images": result["dataset"]["val"], **_scores(result[key])}
            for draw, result in results.items()
        ]
        numbers = [k for k in FIELDS[3:] if k in drawn[0]]
        mean = {k: round(sum(float(r[k]) for r in drawn) / len(drawn), 4) for k in numbers}
        rows += [*drawn, {"model": model, "draw": "mean", "images": sum(r["images"] for r in drawn), **mean}]
    write_csv(Path(__file__).parent / "results.csv", FIELDS, rows)
    print(f"wrote {Path(__file__).parent / 'results.csv'} ({len(rows)} rows)")


if __name__ == "__main__":
    main()
