"""Ground truth for evaluation: labelled points (1 occupied, 0 free) in the map frame.

Three kinds of file are accepted:

* a GeoTIFF (or a GDAL VRT mosaic of them): any single-band raster GDAL reads (any
  TIFF compression or predictor, striped or tiled, COG), north-up in the map frame:
  1 occupied, 0 free, the no-data value (or NaN) for unknown; every labelled cell centre
  becomes a point;
* a ROS map_server YAML with its image, read with map_server's trinary rules: occupied
  cells give 1, free cells 0, unknown cells nothing;
* a labelled point file: CSV with a header naming the columns ``x,y,label`` (other
  columns ignored), or whitespace-separated text with the columns ``x y label`` (an
  optional ``x y label`` header line); ``#`` starts a comment. Every row holds one value
  for each column. Labels are 1 (occupied)
  and 0 or -1 (free). A header may also name a ``kind`` column (``gpocc split`` writes
  ``hit``, ``free`` and ``near-wall``): :func:`load_truth_kinds` returns it, so that
  ``gpocc evaluate`` scores each kind of free point with the occupied points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gpocc.errors import GpoccError, check_regular_file
from gpocc.gridspec import GridSpec
from gpocc.io.carmen import is_number
from gpocc.io.mapserver import read_map_server
from gpocc.io.rasters import read_raster, sample_raster

ACCEPTED = (
    "accepted ground truth: a GeoTIFF or .vrt (1 occupied, 0 free, no-data unknown), "
    "a map_server .yaml with its image, or a point file (.csv with header x,y,label, or "
    "text with columns 'x y label')"
)

_RASTER_SUFFIXES = {".tif", ".tiff", ".vrt"}
_YAML_SUFFIXES = {".yaml", ".yml"}
_POINT_SUFFIXES = {".csv", ".txt", ".xyz", ".dat", ".pts", ".tsv"}
_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def load_truth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ground-truth labelled points from any accepted file (see the module doc).

    Returns:
        ``(points, labels)``: (N, 2) metres in the map frame and (N,) int8, 1 occupied,
        0 free.

    Raises:
        GpoccError: the file is missing, of another kind, malformed, or labels nothing.
    """
    points, labels, _ = load_truth_kinds(path)
    return points, labels


def load_truth_kinds(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`load_truth` plus each point's kind: (N,) str from a point file's ``kind``
    column, None for rasters, map_server maps and point files without one."""
    p = Path(path)
    check_regular_file(p, "ground-truth file", ACCEPTED, missing_fix="check the path")
    suffix = p.suffix.lower()
    kinds = None
    if suffix in _RASTER_SUFFIXES:
        points, labels = _truth_from_raster(p)
    elif suffix in _YAML_SUFFIXES:
        points, labels = _truth_from_map_server(p)
    elif suffix in _POINT_SUFFIXES:
        points, labels, kinds = _truth_from_points(p)
    else:
        with p.open("rb") as fh:
            head = fh.read(4)
        if head in _TIFF_MAGIC:
            points, labels = _truth_from_raster(p)
        else:
            points, labels, kinds = _truth_from_points(p)
    if labels.size == 0:
        raise GpoccError(f"{p}: the ground truth labels no points (all unknown); {ACCEPTED}")
    return points, labels, kinds


def labelled_cell_centres(
    values: np.ndarray, spec: GridSpec, nodata: float | int | None, source: str
) -> tuple[np.ndarray, np.ndarray]:
    """Cell centres (N, 2) metres and labels (N,) of the cells holding 0 or 1.

    Cells equal to ``nodata`` or NaN are unknown and skipped; any other value is an error,
    since a probability map passed as truth would otherwise be silently misread.
    """
    a = np.asarray(values)
    rows, cols = np.nonzero(_known_cells(a, nodata, source))
    x = spec.x0 + (cols + 0.5) * spec.resolution
    y = spec.y0 + (spec.height - rows - 0.5) * spec.resolution
    return np.column_stack([x, y]), a[rows, cols].astype(np.int8)


def _known_cells(a: np.ndarray, nodata: float | int | None, source: str) -> np.ndarray:
    """(H, W) bool: the cells of a truth raster holding a label (0 or 1); an error if any
    other cell holds something but ``nodata`` or NaN."""
    unknown = np.zeros(a.shape, dtype=bool)
    if np.issubdtype(a.dtype, np.floating):
        unknown |= np.isnan(a)
    if nodata is not None and not (isinstance(nodata, float) and np.isnan(nodata)):
        unknown |= a == nodata
    known = ~unknown
    bad = known & (a != 0) & (a != 1)
    if np.any(bad):
        examples = ", ".join(str(v) for v in np.unique(a[bad])[:5])
        raise GpoccError(
            f"{source}: a ground-truth raster must hold 1 (occupied), 0 (free) or its no-data "
            f"value (unknown), found {examples}; threshold it into classes first or set its "
            f"no-data value"
        )
    return known


def labels_at(points: np.ndarray, path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The label a truth raster gives each point: the value of the cell holding it.

    Args:
        points: (N, 2) metres in the map frame.
        path: a GeoTIFF or .vrt (1 occupied, 0 free, no-data unknown) or a map_server
            YAML with its image.

    Returns:
        ``(labels (N,) int8, known (N,) bool)``: 1 occupied, 0 free where ``known``; a
        point outside the raster or on an unknown cell is not known (its label 0).
        A point on an edge shared by two cells takes the cell east of it or north of it
        (:func:`gpocc.io.rasters.sample_raster`).

    Raises:
        GpoccError: the file is missing, not a raster or map_server map, or holds values
            other than 0, 1 and its no-data value.
    """
    p = Path(path)
    check_regular_file(p, "truth raster", "check the path")
    if p.suffix.lower() in _POINT_SUFFIXES:
        raise GpoccError(f"{p}: a point file has no label between its points; pass a truth "
                         "raster (GeoTIFF or .vrt) or a map_server .yaml")
    values, spec, nodata = (_read_map_server_labels(p) if p.suffix.lower() in _YAML_SUFFIXES
                            else read_raster(p))
    _known_cells(np.asarray(values), nodata, str(p))  # refuses a raster of other values
    found, _ = sample_raster(values, spec, nodata, points)
    known = np.isfinite(found)
    labels = np.zeros(len(found), dtype=np.int8)
    labels[known] = found[known]
    return labels, known


def _truth_from_raster(path: Path) -> tuple[np.ndarray, np.ndarray]:
    values, spec, nodata = read_raster(path)
    return labelled_cell_centres(values, spec, nodata, str(path))


def _truth_from_map_server(path: Path) -> tuple[np.ndarray, np.ndarray]:
    return labelled_cell_centres(*_read_map_server_labels(path), str(path))


def write_points(path: str | Path, points: np.ndarray, labels: np.ndarray,
                 kinds: np.ndarray) -> None:
    """Write labelled points as the point file :func:`load_truth_kinds` reads (``gpocc
    split``'s ``heldout.csv``): the header ``x,y,label,kind``, then one row per point,
    metres to 0.1 mm. ``points`` (N, 2) metres; ``labels`` (N,) 1 occupied, 0 free;
    ``kinds`` (N,) str."""
    with Path(path).open("w") as fh:
        fh.write("x,y,label,kind\n")
        fh.writelines(f"{x:.4f},{y:.4f},{int(label):d},{kind}\n" for (x, y), label, kind
                      in zip(points, labels, kinds, strict=True))


def _read_map_server_labels(path: Path) -> tuple[np.ndarray, GridSpec, int]:
    """A map_server map as a truth raster: its classes, grid and no-data value."""
    classes, spec = read_map_server(path)
    # map_server classes: 0 free, 1 occupied, 2 unknown; unknown is our no-data.
    return classes, spec, 2


def _truth_from_points(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    try:
        text = path.read_text(encoding="utf-8-sig")  # a leading BOM (spreadsheets) is no text
    except UnicodeDecodeError:
        raise GpoccError(f"{path}: not a text point file nor a TIFF; {ACCEPTED}") from None
    rows: list[tuple[int, str]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if line:
            rows.append((lineno, line))
    if not rows:
        raise GpoccError(f"{path}: the point file holds no points; {ACCEPTED}")
    comma = "," in rows[0][1]
    split = (lambda s: [t.strip() for t in s.split(",")]) if comma else str.split
    tokens = [(n, split(line)) for n, line in rows]
    columns = (0, 1, 2)
    width, where = 3, "x y label"
    kind_column = None
    first_line, first = tokens[0]
    if not is_number(first[0]):
        names = [t.lower() for t in first]
        missing = [c for c in ("x", "y", "label") if c not in names]
        if missing:
            raise GpoccError(
                f"{path}: line {first_line}: the header must name the columns x, y and label "
                f"(missing {', '.join(missing)}); {ACCEPTED}"
            )
        columns = (names.index("x"), names.index("y"), names.index("label"))
        kind_column = names.index("kind") if "kind" in names else None
        width, where = len(names), f"the header (line {first_line})"
        tokens = tokens[1:]
    elif comma:
        raise GpoccError(f"{path}: a CSV point file needs the header line x,y,label; {ACCEPTED}")
    if not tokens:
        raise GpoccError(f"{path}: the point file holds no points; {ACCEPTED}")
    # A row wider or narrower than the header (or than x y label) is a shifted or
    # mis-split file: which value is which column cannot be known.
    for lineno, row in tokens:
        if len(row) != width:
            raise GpoccError(
                f"{path}: line {lineno}: expected {width} values, one for each column of "
                f"{where}, got {len(row)}; {ACCEPTED}"
            )
    try:
        table = np.array([[row[c] for c in columns] for _, row in tokens], dtype=float)
    except ValueError:
        for lineno, row in tokens:
            if not all(is_number(row[c]) for c in columns):
                raise GpoccError(
                    f"{path}: line {lineno}: x, y and label must be numbers, got "
                    f"{' '.join(row[c] for c in columns)!r}"
                ) from None
        raise  # pragma: no cover - every row parsed one by one
    finite = np.isfinite(table[:, :2]).all(axis=1)
    raw_labels = table[:, 2]
    valid = (raw_labels == 1) | (raw_labels == 0) | (raw_labels == -1)
    bad = np.flatnonzero(~(finite & valid))
    if bad.size:
        lineno, row = tokens[int(bad[0])]
        raise GpoccError(
            f"{path}: line {lineno}: x and y must be finite and the label 1 (occupied) or "
            f"0 / -1 (free), got {' '.join(row[c] for c in columns)!r}"
        )
    kinds = (None if kind_column is None
             else np.array([row[kind_column] for _, row in tokens], dtype=str))
    return table[:, :2].copy(), (raw_labels == 1).astype(np.int8), kinds
