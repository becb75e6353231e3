"""GPS fixes recorded inside a GoPro video (GPMF telemetry, HERO5 and later), read with telemetry-parser (the Rust
parser behind Gyroflow, maintained; it also reads Sony, Insta360 and DJI telemetry).

GoPro stores about one second of fixes per telemetry sample: a GPS5 array (lat, lon, alt, 2D and 3D speed, scaled
integers, ~18 Hz), its SCAL, the fix type GPSF and GPSU, the UTC time of the sample's first fix. Each fix's time is
spread evenly over its sample's period (the median step between GPSU times). The telemetry track starts with the
video and the camera writes a GPS sample every period even before its first fix, so the video's start time is the
first kept sample's GPSU less its place among the GPS samples times the period, unless --video-start-utc is given.
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


def _samples(video: Path) -> list[tuple[int, int, np.ndarray]]:
    """(place among the GPS samples, GPSU ms, (n, 3) lat deg, lon deg, alt m) of every telemetry sample with a GPS
    fix, in file order."""
    import telemetry_parser  # a compiled extension, only for videos

    try:
        telemetry = telemetry_parser.Parser(str(video)).telemetry()
    except Exception:  # noqa: BLE001 - it raises for every format it does not know (a plain MP4): no telemetry
        return []
    samples = []
    gps_groups = [sample["GPS"] for sample in telemetry or [] if sample.get("GPS")]
    for place, gps in enumerate(gps_groups):
        data, scale, utc_ms = gps.get("Data"), gps.get("Scale"), _tag(gps, _GPSU)
        fix = _tag(gps, _GPSF)
        if not data or not scale or utc_ms is None or (fix is not None and int(fix) < MIN_FIX_TYPE):
            continue
        rows = np.asarray(data, dtype=float)
        if rows.ndim != 2 or rows.shape[1] < 3:
            continue
        samples.append((place, int(utc_ms), rows[:, :3] / np.asarray(scale, dtype=float)[:3]))
    return samples


def read_gopro_gps(video: Path) -> GpsTrack | None:
    """The GPS track recorded inside a GoPro video, or None when it has none (no telemetry, or no fix).

    :raises InputError: the telemetry has fewer than 2 fixes.
    """
    samples = _samples(video)
    if not samples:
        return None
    places = np.array([s[0] for s in samples], dtype=float)
    starts_ms = np.array([s[1] for s in samples], dtype=float)
    period_ms = float(np.median(np.diff(starts_ms) / np.diff(places))) if len(samples) > 1 else 1000.0
    times = [
        start_ms + period_ms * np.arange(len(rows)) / len(rows)
        for (_, _, rows), start_ms in zip(samples, starts_ms, strict=True)
    ]
    t_ns = np.round(np.concatenate(times) * 1e6).astype(np.int64)
    order = np.argsort(t_ns, kind="stable")  # a GPSU a little early would put its fixes before the last sample's
    t_ns, a = t_ns[order], np.concatenate([rows for _, _, rows in samples])[order]
    keep = np.concatenate([[True], np.diff(t_ns) > 0])
    if keep.sum() < 2:
        count = int(keep.sum())
        raise InputError(f"the video's GoPro telemetry has {count} GPS fix(es); a track needs at least 2", video)
    video_start_ns = round((starts_ms[0] - places[0] * period_ms) * 1e6)
    return GpsTrack(t_ns[keep], a[keep, 0], a[keep, 1], a[keep, 2], video, kind="gpmf", video_start_ns=video_start_ns)
