"""GSV-Cities (Ali-bey et al., Neurocomputing 2022) as training places: the layout its dataloader reads.

``<root>/Dataframes/<City>.csv`` holds one row per image with the columns ``place_id, year, month,
northdeg, city_id, lat, lon, panoid``; the image is ``<root>/Images/<city_id>/<name>``, its name built
from the row as gsv-cities builds it::

    <city_id>_<place_id mod 10^5, 7 digits>_<year, 4>_<month, 2>_<northdeg, 3>_<lat>_<lon>_<panoid>.jpg

(numbers zero-padded, ``lat`` / ``lon`` as Python prints the float read from the file). A place is a
(city, place_id) pair; places are grouped by city, in the order the cities are given. Images are the
set's database side (there are no queries); their positions are metres on a local equirectangular
projection of each city, cities 10,000 km apart, so that places of two cities are never within any
radius of each other.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from semvpr.core.errors import SemvprError
from semvpr.core.io import regular_file
from semvpr.data.places import PlaceIds, PlaceSet, listed_image

COLUMNS = ("place_id", "year", "month", "northdeg", "city_id", "lat", "lon", "panoid")
WHOLE = ("place_id", "year", "month", "northdeg")
#: Metres per degree of latitude (mean Earth radius 6,371 km).
M_PER_DEGREE = 6_371_000.0 * math.pi / 180.0
CITY_SHIFT_M = 1e7


class Row(NamedTuple):
    """One row of a city's dataframe, typed (``COLUMNS``, in order)."""

    place_id: int
    year: int
    month: int
    northdeg: int
    city_id: str
    lat: float
    lon: float
    panoid: str


def image_name(row: Row) -> str:
    """The file name of one row, as gsv-cities' dataloader builds it."""
    fields = [
        row.city_id,
        str(row.place_id % 10**5).zfill(7),
        str(row.year).zfill(4),
        str(row.month).zfill(2),
        str(row.northdeg).zfill(3),
        str(row.lat),
        str(row.lon),
        row.panoid,
    ]
    return "_".join(fields) + ".jpg"


def _row(row: dict[str, str], line: int, path: Path) -> Row:
    """One csv row as typed values, or one line naming the file, the line and the field."""
    values: dict[str, object] = {}
    for key in COLUMNS:
        text = (row.get(key) or "").strip()
        try:
            if key in WHOLE:
                values[key] = int(text)
            elif key in ("lat", "lon"):
                values[key] = float(text)
                if not math.isfinite(values[key]):  # type: ignore[arg-type]
                    raise ValueError
            else:
                if not text or "/" in text or "\\" in text or text in (".", ".."):
                    raise ValueError
                values[key] = text
        except ValueError:
            kind = "a whole number" if key in WHOLE else "a number" if key in ("lat", "lon") else "a name"
            raise SemvprError(f"{path}: line {line}: {key}={text!r} is not {kind}") from None
    return Row(*(values[k] for k in COLUMNS))  # type: ignore[arg-type]


def _city_rows(path: Path) -> list[Row]:
    """The typed rows of one city's dataframe: a regular UTF-8 csv file; anything else is one line naming it."""
    regular_file(path, "GSV-Cities dataframe")
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        rows = []
        try:
            missing = [c for c in COLUMNS if c not in (reader.fieldnames or ())]
            if missing:
                raise SemvprError(f"{path}: missing column(s) {missing}; a GSV-Cities dataframe has {list(COLUMNS)}")
            for row in reader:
                rows.append(_row(row, reader.line_num, path))
        except csv.Error as err:
            raise SemvprError(f"{path}: line {reader.line_num + 1}: not a readable csv row ({err})") from None
        except UnicodeDecodeError as err:
            byte = err.object[err.start : err.start + 1].hex()
            raise SemvprError(
                f"{path}: not UTF-8 text (a byte 0x{byte}); a GSV-Cities dataframe is UTF-8 csv"
            ) from None
    if not rows:
        raise SemvprError(f"{path}: no rows")
    return rows


def read_gsv_cities(root: str | Path, cities: list[str] | None = None) -> PlaceSet:
    """The images of ``cities`` (csv names in ``Dataframes/``; None: every csv there, sorted) as places."""
    root = Path(root).expanduser()
    frames = root / "Dataframes"
    if not frames.is_dir() or not (root / "Images").is_dir():
        raise SemvprError(
            f"GSV-Cities folders {frames} / {root / 'Images'} not found; set data.root=... to the folder "
            "holding Dataframes/ and Images/"
        )
    found = sorted(p.stem for p in frames.glob("*.csv"))
    cities = found if cities is None else [str(c) for c in cities]
    if not cities:
        raise SemvprError(f"{frames}: no <City>.csv dataframe")
    unknown = [c for c in cities if c not in found]
    if unknown:
        raise SemvprError(f"{frames}: no dataframe for city {unknown[0]!r} (found {found}); check data.cities")
    paths: list[Path] = []
    utm: list[np.ndarray] = []
    place_of: dict[tuple[int, int], int] = {}
    ids: list[int] = []
    groups: list[int] = []
    for city_index, city in enumerate(cities):
        csv_path = frames / f"{city}.csv"
        rows = _city_rows(csv_path)
        listed: dict[str, set[str]] = {}
        missing: list[Path] = []
        for row in rows:
            folder = root / "Images" / row.city_id
            if row.city_id not in listed:
                listed[row.city_id] = {p.name for p in folder.iterdir()} if folder.is_dir() else set()
            name = image_name(row)
            path = listed_image(folder, name, csv_path)
            if name not in listed[row.city_id]:
                missing.append(path)
            paths.append(path)
            key = (city_index, row.place_id)
            if key not in place_of:
                place_of[key] = len(place_of)
                groups.append(city_index)
            ids.append(place_of[key])
        if missing:
            raise SemvprError(
                f"{csv_path}: {len(missing)} of its {len(rows)} images are missing, the first {missing[0]}; "
                "the names are built from each row as gsv-cities builds them"
            )
        lat_lon = np.array([(r.lat, r.lon) for r in rows], dtype=np.float64)
        lat0, lon0 = lat_lon.mean(0)
        east = (lat_lon[:, 1] - lon0) * M_PER_DEGREE * math.cos(math.radians(lat0)) + city_index * CITY_SHIFT_M
        north = (lat_lon[:, 0] - lat0) * M_PER_DEGREE
        utm.append(np.stack([east, north], 1))
    label = "+".join(cities) if len(cities) <= 3 else f"{len(cities)} cities"
    return PlaceSet(
        name=f"gsv-cities/{label}",
        db_paths=tuple(paths),
        q_paths=(),
        db_utm=np.concatenate(utm),
        q_utm=np.zeros((0, 2)),
        root=root,
        place_ids=PlaceIds(db=np.array(ids), q=np.zeros(0, np.int64), groups=np.array(groups)),
    )
