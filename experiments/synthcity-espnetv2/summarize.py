"""results.csv of the synthcity-espnetv2 runs (run.sh OUT): per SynthCity draw, ESPNetv2's scores on the draw's
segmentation val split (results.json of each ``semvpr.segment`` run), a row per draw and their mean.

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
FIELDS = ("model", "draw", "images", *SCORES, *(f"iou_{c}" for c in CLASSES))


@exit_on_user_error
def main() -> None:
    out = summary_input(__doc__.splitlines()[0], "experiments/synthcity-espnetv2/run.sh")
    rows = []
    for draw in DRAWS:
        result = read_json(out / f"segment-s{draw}" / "results.json", "a semvpr.segment result")
        scores = result["teacher"]["val"]
        if Path(result["dataset"]["root"]).parent.name != f"synthcity-s{draw}":
            raise SemvprError(f"{out}/segment-s{draw} scored {result['dataset']['root']}, not draw {draw}'s city")
        rows.append({
            "model": "ESPNetv2 s=2.0 (Cityscapes)", "draw": draw, "images": result["dataset"]["val"],
            **{k: round(scores[k], 4) for k in SCORES},
            **{f"iou_{c}": round(scores["class_iou"][c], 4) for c in CLASSES},
        })  # fmt: skip
    numbers = (*SCORES, *(f"iou_{c}" for c in CLASSES))
    mean = {k: round(sum(float(r[k]) for r in rows) / len(rows), 4) for k in numbers}
    rows.append({"model": rows[0]["model"], "draw": "mean", "images": sum(r["images"] for r in rows), **mean})
    write_csv(Path(__file__).parent / "results.csv", FIELDS, rows)
    print(f"wrote {Path(__file__).parent / 'results.csv'} ({len(rows)} draws)")


if __name__ == "__main__":
    main()
