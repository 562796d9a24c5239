"""Figure of SynthCity pairs: query, its nearest database capture, and both dynamic masks.

    python experiments/synthcity-sample/make_figure.py [--root DIR] [--out sample.png]

Without --root the default preset (seed 0) is generated into / read from outputs/cache.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from semvpr.data.synthcity import read_split  # noqa: E402
from semvpr.data.synthcity_render import DYNAMIC_MIN  # noqa: E402


def overlay(image: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Image with dynamic / uninformative pixels (trainId >= 10) tinted red."""
    out = image.astype(np.float32) / 255
    dyn = label >= DYNAMIC_MIN
    out[dyn] = 0.45 * out[dyn] + 0.55 * np.array([1.0, 0.1, 0.1])
    return out


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
        titles = ["query", "query: dynamic (red)", f"nearest database ({dist:.1f} m)", "database: dynamic (red)"]
        for ax, panel, title in zip(row, [panels[0], panels[1], panels[2], panels[3]], titles):
            ax.imshow(panel)
            ax.set_title(title, fontsize=9)
            ax.axis("off")
    fig.suptitle("SynthCity default preset, test split: same place, two traversals (other time, other road users)")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp.png")
    fig.savefig(tmp, dpi=90)
    tmp.rename(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
