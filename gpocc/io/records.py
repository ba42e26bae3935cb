"""What a model was built from: one record per input (path, content hash, scans, time
span, transform), kept in the model file and listed by ``gpocc info`` and
``metadata.json``; ``gpocc update`` refuses an input whose content is already in."""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gpocc.config import Config, TransformConfig
from gpocc.errors import GpoccError, check_regular_file
from gpocc.io.frames import IDENTITY, input_transform
from gpocc.io.scans import ScanBatch
from gpocc.progress import log

_BLOCK = 1 << 20


@dataclass(frozen=True)
class InputRecord:
    """One input of a model.

    Attributes:
        path: as given on the command line.
        sha256: hex digest of its content (a bag folder: of its files' names and
            contents); empty when not known (models written before it was kept).
        scans: scans read from it (all sensors).
        start_s, end_s: first and last scan stamp, seconds (None: no scans or not known).
        sensors: the sensors read from it.
        transform: (x_m, y_m, yaw_deg) applied to its poses (config ``inputs``).
    """

    path: str
    sha256: str = ""
    scans: int = 0
    start_s: float | None = None
    end_s: float | None = None
    sensors: tuple[str, ...] = ()
    transform: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def as_dict(self) -> dict[str, Any]:
        """Plain data for JSON (model file, ``metadata.json``)."""
        data = dataclasses.asdict(self)
        data["sensors"] = list(self.sensors)
        data["transform"] = dict(zip(("x_m", "y_m", "yaw_deg"), self.transform, strict=True))
        return data


def content_hash(path: str | Path) -> str:
    """SHA-256 of a file, or of a folder's files (relative names and contents, sorted)."""
    path = Path(path)
    if not path.is_dir():
        check_regular_file(path, "recording", "check the input path")
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        if path.is_dir():
            digest.update(file.relative_to(path).as_posix().encode() + b"\0")
        with file.open("rb") as fh:
            while block := fh.read(_BLOCK):
                digest.update(block)
    return digest.hexdigest()


def input_records(paths: Sequence[str | Path], batches: Sequence[ScanBatch],
                  config: Config, hashes: Sequence[str] | None = None
                  ) -> tuple[InputRecord, ...]:
    """One record per input of ``paths``, from the batches read from it; ``hashes``:
    their :func:`content_hash` when already known."""
    if hashes is None:
        hashes = [content_hash(p) for p in paths]
    records = []
    for path, digest in zip(paths, hashes, strict=True):
        own = [b for b in batches if b.source == str(Path(path))]
        stamps = [b.stamps for b in own if b.n_scans]
        t = input_transform(path, config)
        records.append(InputRecord(
            path=str(path), sha256=digest, scans=sum(b.n_scans for b in own),
            start_s=float(min(s.min() for s in stamps)) if stamps else None,
            end_s=float(max(s.max() for s in stamps)) if stamps else None,
            sensors=tuple(dict.fromkeys(b.sensor for b in own)),
            transform=(t.x_m, t.y_m, t.yaw_deg)))
    return tuple(records)


def check_new_inputs(known: Sequence[InputRecord], paths: Sequence[str | Path],
                     hashes: Sequence[str], model: str) -> None:
    """Refuse an input whose content (``hashes``, :func:`content_hash`) is already in the
    model or given twice.

    Raises:
        GpoccError: naming the input, the model and the input it repeats.
    """
    seen = {r.sha256: f"'{r.path}' in {model}" for r in known if r.sha256}
    for path, digest in zip(paths, hashes, strict=True):
        if digest in seen:
            raise GpoccError(
                f"{path}: this log is already in the model (same content as {seen[digest]}); "
                "pass only logs the model does not hold yet")
        seen[digest] = f"'{path}', given twice"


def warn_repeated_content(paths: Sequence[str | Path], hashes: Sequence[str],
                          config: Config | None = None) -> None:
    """A warning for each input whose content (``hashes``) an earlier one already has:
    two names of one log, whose scans then count twice, unless ``config``'s ``inputs``
    entries give the two different transforms (one log placed twice on a site)."""
    first: dict[tuple[str, TransformConfig], int] = {}
    for i, (path, digest) in enumerate(zip(paths, hashes, strict=True)):
        placed = input_transform(path, config) if config is not None else IDENTITY
        earlier = first.setdefault((digest, placed), i)
        if earlier != i:
            log(f"warning: {path} has the same content as {paths[earlier]}: its scans count "
                "twice, unless the config's inputs entries place them apart")


def record_from_dict(data: Any) -> InputRecord:
    """An :class:`InputRecord` from its :meth:`~InputRecord.as_dict` form.

    Raises:
        ValueError: a field is missing or of the wrong type.
    """
    if not isinstance(data, dict) or not isinstance(data.get("path"), str):
        raise ValueError(f"input record {data!r} has no path")
    transform = data.get("transform", {})
    if not isinstance(transform, dict):
        raise ValueError(f"input record {data['path']!r}: transform is not a mapping")
    values = [transform.get(k, 0.0) for k in ("x_m", "y_m", "yaw_deg")]
    span = [data.get("start_s"), data.get("end_s")]
    numbers = [*values, *(v for v in span if v is not None)]
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in numbers):
        raise ValueError(f"input record {data['path']!r} holds a non-number")
    scans = data.get("scans", 0)
    sensors = data.get("sensors", [])
    if (isinstance(scans, bool) or not isinstance(scans, int) or scans < 0
            or not isinstance(sensors, list) or not all(isinstance(s, str) for s in sensors)
            or not isinstance(data.get("sha256", ""), str)):
        raise ValueError(f"input record {data['path']!r} is malformed")
    return InputRecord(
        path=data["path"], sha256=data.get("sha256", ""), scans=scans,
        start_s=None if span[0] is None else float(span[0]),
        end_s=None if span[1] is None else float(span[1]),
        sensors=tuple(sensors), transform=tuple(float(v) for v in values))  # type: ignore[arg-type]
