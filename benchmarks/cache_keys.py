"""What keying the image caches by content costs on a Pitts30k-size name list.

Every image cache (trunk, masks, descriptors, pseudo-labels) is keyed by each image's name below
the dataset root, size and mtime (``PlaceSet.identity``: one ``stat`` per file, no read). This
writes the real Pitts30k-test names (10,000 database + 6,816 query images, from
``../shared/realdata``; numbered placeholders when absent) as small placeholder files and times
the keys of both sides: the first call (inodes possibly not cached yet) and the median of the
others. Measured on the 2-core AMD EPYC dev machine: 0.39-0.56 s first, 0.40-0.42 s warm for
16,816 images (24-25 us each), where the frozen VGG16 trunk pass over the same images takes
minutes (at 480x640 on CPU a few images/s; on a GPU even 1,000 images/s is 17 s).

    python benchmarks/cache_keys.py [--dir /tmp/cache-keys] [--repeat 5]

Last line: ``images=<n> first_s=<s> warm_s=<s> per_image_us=<us>``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from semvpr.data.places import PlaceSet

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"


def names() -> tuple[list[str], list[str]]:
    """Pitts30k-test's database and query names (relative to the dataset root)."""
    db, q = REALDATA / "pitts30k_test_dbImages.npy", REALDATA / "pitts30k_test_qImages.npy"
    if db.is_file() and q.is_file():
        return [str(n) for n in np.load(db)], [str(n) for n in np.load(q)]
    return (
        [f"{i // 1000:03d}/{i:06d}_pitch1_yaw1.jpg" for i in range(10_000)],
        [f"queries_real/{i // 1000:03d}/{i:06d}_pitch1_yaw1.jpg" for i in range(6_816)],
    )


def main() -> None:
    """Write the placeholders once, then time PlaceSet.identity over both sides."""
    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--dir", type=Path, default=Path("/tmp/cache-keys"))
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    db, q = names()
    root = args.dir / "pitts30k"
    for name in db + q:
        path = root / name
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(b"\xff\xd8placeholder")
    places = PlaceSet(
        "pitts30k/test",
        [root / n for n in db],
        [root / n for n in q],
        np.zeros((len(db), 2)),
        np.zeros((len(q), 2)),
        root=root,
    )
    times = []
    for _ in range(args.repeat):
        tic = time.perf_counter()
        places.identity("db"), places.identity("q")
        times.append(time.perf_counter() - tic)
    n = len(db) + len(q)
    warm = statistics.median(times[1:]) if len(times) > 1 else times[0]
    print(f"images={n} first_s={times[0]:.3f} warm_s={warm:.3f} per_image_us={1e6 * warm / n:.1f}")


if __name__ == "__main__":
    main()
