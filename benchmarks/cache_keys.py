"""What keying the image caches by content costs on a Pitts30k-size name list, against a stat-only key.

Every image cache (trunk, masks, descriptors, pseudo-labels) is keyed by each image's name below the
dataset root, size and a SHA-256 of its first, middle and last 4 KiB (``PlaceSet.identity`` through
``core.cache.files_identity``), so an image replaced by another of the same size gets another key and a
copied dataset (new mtimes) keeps its caches. A key of the name, size and mtime alone (one ``stat`` per
file, no read) is timed in the same run as the reference. This writes the real Pitts30k-test names
(10,000 database + 6,816 query images, from ``../shared/realdata``; numbered placeholders when absent) as
placeholder files of ``--image-bytes`` (default 80 KiB, a Pitts30k JPEG's order: 4 KiB of data at each
end, the rest left sparse) and times both keys over both sides: the first call and the median of the
others. The files were just written, so both run on a warm page cache; a cold cache adds three disk
reads per image to the content key (still far below decoding the image, which the trunk pass does
anyway).

    python benchmarks/cache_keys.py [--dir /tmp/cache-keys] [--repeat 5] [--image-bytes 81920]

Last line: ``images=<n> stat_first_s=<s> stat_warm_s=<s> content_first_s=<s> content_warm_s=<s>
stat_us=<us per image> content_us=<us per image> ratio=<content / stat, warm>``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from semvpr.core.errors import exit_on_user_error
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


def write_placeholder(path: Path, size: int, seed: int) -> None:
    """A file of ``size`` bytes with distinct data in its first and last 4 KiB (the middle sparse)."""
    if path.is_file() and path.stat().st_size == size:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    end = min(4096, size // 2)
    with open(path, "wb") as fh:
        fh.write(b"\xff\xd8" + rng.bytes(end - 2))
        fh.seek(size - end)
        fh.write(rng.bytes(end))


def stat_identity(names_: list[str], paths: list[Path]) -> str:
    """The stat-only reference key: each file's name, size and mtime (one stat, no read)."""
    digest = hashlib.sha256()
    for name, path in zip(names_, paths, strict=True):
        st = os.stat(path)
        digest.update(f"{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:16]


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(first call, median of the others) in seconds."""
    times = []
    for _ in range(repeat):
        tic = time.perf_counter()
        fn()
        times.append(time.perf_counter() - tic)
    return times[0], statistics.median(times[1:]) if len(times) > 1 else times[0]


@exit_on_user_error
def main() -> None:
    """Write the placeholders once, then time both keys over both sides."""
    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--dir", type=Path, default=Path("/tmp/cache-keys"))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--image-bytes", type=int, default=80 * 1024)
    ap.add_argument("--limit", type=int, default=None, help="use only the first N names of each side (smoke runs)")
    args = ap.parse_args()
    db, q = names()
    db, q = db[: args.limit], q[: args.limit]
    root = args.dir / "pitts30k"
    for i, name in enumerate(db + q):
        write_placeholder(root / name, args.image_bytes, i)
    db_paths, q_paths = [root / n for n in db], [root / n for n in q]
    places = PlaceSet("pitts30k/test", db_paths, q_paths, np.zeros((len(db), 2)), np.zeros((len(q), 2)), root=root)
    # The stat key first: its stats warm the inode cache for both.
    stat_first, stat_warm = timed(lambda: (stat_identity(db, db_paths), stat_identity(q, q_paths)), args.repeat)

    def content_key() -> tuple[str, str]:
        fresh = dataclasses.replace(places)  # a set takes its key once: each repeat is a new run's set
        return fresh.identity("db"), fresh.identity("q")

    content_first, content_warm = timed(content_key, args.repeat)
    n = len(db) + len(q)
    print(
        f"images={n} stat_first_s={stat_first:.3f} stat_warm_s={stat_warm:.3f} content_first_s={content_first:.3f} "
        f"content_warm_s={content_warm:.3f} stat_us={1e6 * stat_warm / n:.1f} content_us={1e6 * content_warm / n:.1f} "
        f"ratio={content_warm / stat_warm:.2f}"
    )


if __name__ == "__main__":
    main()
