"""Figure of SynthCity pairs: query, its nearest database capture, and both class-group overlays.

    PYTHONPATH=. python experiments/synthcity-sample/make_figure.py [--cache-dir outputs/cache] [--out sample.png]

The default preset (seed 0) is generated into / read from the cache directory. Overlays tint each
class group by the phenomenon it models (see semvpr/data/synthcity_render.py).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from semvpr.core.errors import exit_on_user_error  # noqa: E402
from semvpr.data.synthcity import read_split  # noqa: E402
from semvpr.data.synthcity_render import (
    DYNAMIC_MIN,
    LIGHT,
    POLE,
    ROAD,
    SIDEWALK,
    SIGN,
    TERRAIN,  # noqa: E402
    VEG,
)

# Class group → tint: dynamic/sky (misleading), seasonal vegetation, aliased ground, place-specific furniture.
TINTS = (
    ("dynamic / sky", lambda lab: lab >= DYNAMIC_MIN, (1.0, 0.1, 0.1)),
    ("vegetation (season)", lambda lab: np.isin(lab, (VEG, TERRAIN)), (1.0, 0.9, 0.0)),
    ("road, sidewalk (aliasing, parallax)", lambda lab: np.isin(lab, (ROAD, SIDEWALK)), (0.1, 0.4, 1.0)),
    ("poles, signs (per place)", lambda lab: np.isin(lab, (POLE, SIGN, LIGHT)), (1.0, 0.0, 1.0)),
)


def overlay(image: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Image with each class group tinted; facades (buildings, walls, fences) left as they are."""
    out = image.astype(np.float32) / 255
    for _, members, tint in TINTS:
        m = members(label)
        out[m] = 0.45 * out[m] + 0.55 * np.array(tint)
    return out


@exit_on_user_error
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache-dir", default="outputs/cache")
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--out", type=Path, default=Path(__file__).with_name("sample.png"))
    args = ap.parse_args()
    test = read_split("default", 0, args.cache_dir, "test")
    positives = test.positives(25.0)
    picks = np.linspace(0, len(test.q_paths) - 1, args.pairs).astype(int)
    fig, axes = plt.subplots(args.pairs, 4, figsize=(12, 2.4 * args.pairs))
    for row, qi in zip(axes, picks):
        di = int(positives[qi][0])
        dist = float(np.linalg.norm(test.q_utm[qi] - test.db_utm[di]))
        panels = []
        for path, lab in ((test.q_paths[qi], test.q_labels[qi]), (test.db_paths[di], test.db_labels[di])):
            img, label = np.asarray(Image.open(path).convert("RGB")), np.asarray(Image.open(lab))
            panels += [img, overlay(img, label)]
        titles = [
            "query (November)",
            "query: class groups",
            f"nearest database, June ({dist:.1f} m)",
            "database: class groups",
        ]
        for ax, panel, title in zip(row, [panels[0], panels[1], panels[2], panels[3]], titles):
            ax.imshow(panel)
            ax.set_title(title, fontsize=9)
            ax.axis("off")
    legend = ", ".join(f"{name} {('red', 'yellow', 'blue', 'magenta')[i]}" for i, (name, *_) in enumerate(TINTS))
    fig.suptitle(
        "SynthCity default preset, test split: same place, two traversals (season, light, road users)\n" + legend,
        fontsize=10,
    )
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp.png")
    fig.savefig(tmp, dpi=90)
    tmp.rename(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
