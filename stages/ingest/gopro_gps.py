"""GPS fixes recorded inside a GoPro video (GPMF telemetry, HERO5 and later), read with telemetry-parser (the Rust
parser behind Gyroflow, maintained; it also reads Sony, Insta360 and DJI telemetry).

GoPro stores about one second of fixes per telemetry sample: a GPS5 array (lat, lon, alt, 2D and 3D speed, scaled
integers, ~18 Hz), its SCAL, the fix type GPSF and GPSU, the UTC time of the sample's first fix. Each fix's time is
spread evenly from its sample's GPSU to the next one's. The telemetry track starts with the video, so the first fix's
time is the video's start time unless --video-start-utc says otherwise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.stages.ingest.gps_sidecar import GpsTrack

_GPSU = ("GPSU", "0x47505355")  # telemetry-parser names tags it has no name for by their FourCC in hex
_GPSF = ("GPSF", "0x47505346")
MIN_FIX_TYPE = 2  # GPSF: 0 no fix, 2 a 2D fix, 3 a 3D fix


def _tag(group: dict, names: tuple[str, ...]) -> object:
    """The value of the first of `names` in a telemetry group, or None."""
    return next((group[n] for n in names if n in group), None)


def _samples(video: Path) -> list[tuple[int, np.ndarray]]:
    """(GPSU ms, (n, 3) lat deg, lon deg, alt m) of every telemetry sample with a GPS fix, in file order."""
    import telemetry_parser  # a compiled extension, only for videos

    try:
        telemetry = telemetry_parser.Parser(str(video)).telemetry()
    except Exception:  # noqa: BLE001 - it raises for every format it does not know (a plain MP4): no telemetry
        return []
    samples = []
    for sample in telemetry or []:
        gps = sample.get("GPS") or {}
        data, scale, utc_ms = gps.get("Data"), gps.get("Scale"), _tag(gps, _GPSU)
        fix = _tag(gps, _GPSF)
        if not data or not scale or utc_ms is None or (fix is not None and int(fix) < MIN_FIX_TYPE):
            continue
        rows = np.asarray(data, dtype=float)
        if rows.ndim != 2 or rows.shape[1] < 3:
            continue
        samples.append((int(utc_ms), rows[:, :3] / np.asarray(scale, dtype=float)[:3]))
    return samples


def read_gopro_gps(video: Path) -> GpsTrack | None:
    """The GPS track recorded inside a GoPro video, or None when it has none (no telemetry, or no fix).

    :raises InputError: the telemetry has fewer than 2 fixes.
    """
    samples = _samples(video)
    if not samples:
        return None
    starts_ms = np.array([s[0] for s in samples], dtype=float)
    steps_ms = np.diff(starts_ms)
    last_ms = float(np.median(steps_ms)) if len(steps_ms) else 1000.0
    ends_ms = np.append(starts_ms[1:], starts_ms[-1] + last_ms)
    times, fixes = [], []
    for (_, rows), start_ms, end_ms in zip(samples, starts_ms, ends_ms, strict=True):
        times.append(start_ms + (end_ms - start_ms) * np.arange(len(rows)) / len(rows))
        fixes.append(rows)
    t_ns = np.round(np.concatenate(times) * 1e6).astype(np.int64)
    a = np.concatenate(fixes)
    keep = np.concatenate([[True], np.diff(t_ns) > 0])
    if keep.sum() < 2:
        count = int(keep.sum())
        raise InputError(f"the video's GoPro telemetry has {count} GPS fix(es); a track needs at least 2", video)
    return GpsTrack(t_ns[keep], a[keep, 0], a[keep, 1], a[keep, 2], video, kind="gpmf")
