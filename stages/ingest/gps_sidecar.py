"""GPS tracks beside a video: GPX (gpxpy), NMEA 0183 (pynmea2: RMC for date and position, GGA for altitude) or CSV
with a header naming latitude, longitude and time columns (ISO 8601 or Unix seconds) and optionally altitude.

Times are int64 ns since the Unix epoch (UTC); positions WGS84 degrees, altitude metres (NaN when absent).
"""

from __future__ import annotations

import csv
import datetime as dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import Transformer

from drivesim.pipeline.errors import InputError

SIDECAR_SUFFIXES = (".gpx", ".nmea", ".csv")
_LAT = ("lat", "latitude", "lat_deg")
_LON = ("lon", "lng", "long", "longitude", "lon_deg")
_TIME = ("time", "timestamp", "utc", "datetime", "t", "time_s", "unix_time")
_ALT = ("alt", "altitude", "ele", "elevation", "alt_m")


@dataclass(frozen=True)
class GpsTrack:
    """Fixes of a GPS sidecar, sorted by time.

    :param t_ns: (M,) UTC ns since the Unix epoch.
    :param lat_deg, lon_deg: (M,) WGS84.
    :param alt_m: (M,) height (NaN when the file has none).
    :param path: the file read.
    :param kind: what was read ("gpmf": a GoPro video's telemetry); "" for a sidecar (its suffix says).
    :param video_start_ns: UTC ns of the video's first frame when the track says it (a GoPro's), else None.
    """

    t_ns: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    path: Path
    kind: str = ""
    video_start_ns: int | None = None

    def enu_m(self) -> np.ndarray:
        """(M, 3) east/north/up metres about the first fix (heights 0 where absent)."""
        alt = np.where(np.isfinite(self.alt_m), self.alt_m, 0.0)
        lat0, lon0, h0 = float(self.lat_deg[0]), float(self.lon_deg[0]), float(alt[0])
        transformer = Transformer.from_pipeline(
            "+proj=pipeline +step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0={h0!r}"
        )
        e, n, u = transformer.transform(self.lon_deg, self.lat_deg, alt)
        return np.column_stack([e, n, u])


def find_sidecar(video: Path) -> Path | None:
    """A .gpx/.nmea/.csv file with the video's name beside it (drive.mp4 -> drive.gpx), or None."""
    for suffix in SIDECAR_SUFFIXES:
        for candidate in (video.with_suffix(suffix), video.with_suffix(suffix.upper())):
            if candidate.is_file():
                return candidate
    return None


def _ns(when: dt.datetime) -> int:
    if when.tzinfo is None:
        when = when.replace(tzinfo=dt.UTC)
    return round(when.timestamp() * 1e9)


def _track(rows: list[tuple[int, float, float, float]], path: Path) -> GpsTrack:
    if len(rows) < 2:
        raise InputError(f"the GPS file has {len(rows)} timed fix(es); a track needs at least 2", path)
    a = np.array(rows, dtype=float)
    order = np.argsort(a[:, 0], kind="stable")
    t_ns = np.array([rows[i][0] for i in order], dtype=np.int64)
    keep = np.concatenate([[True], np.diff(t_ns) > 0])
    a = a[order][keep]
    return GpsTrack(t_ns[keep], a[:, 1], a[:, 2], a[:, 3], path)


def read_gpx(path: Path) -> GpsTrack:
    """Track points (with a time) of every track and segment of a GPX file."""
    import gpxpy
    import gpxpy.gpx

    try:
        gpx = gpxpy.parse(path.read_text())
    except (OSError, UnicodeDecodeError, gpxpy.gpx.GPXException) as e:
        raise InputError(f"unreadable GPX file ({type(e).__name__}: {str(e).splitlines()[0][:120]})", path) from e
    rows = [
        (_ns(p.time), p.latitude, p.longitude, np.nan if p.elevation is None else p.elevation)
        for track in gpx.tracks
        for segment in track.segments
        for p in segment.points
        if p.time is not None
    ]
    return _track(rows, path)


def read_nmea(path: Path) -> GpsTrack:
    """Fixes of an NMEA log: RMC sentences give date, time and position; GGA ones the altitude at the same time."""
    import pynmea2

    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as e:
        raise InputError(f"cannot read the NMEA file: {e.strerror}", path) from e
    fixes: dict[int, list[float]] = {}
    altitude: dict[dt.time, float] = {}
    for line in lines:
        try:
            msg = pynmea2.parse(line.strip())
        except (pynmea2.ParseError, ValueError):
            continue
        if isinstance(msg, pynmea2.types.talker.GGA) and msg.timestamp and msg.altitude is not None:
            altitude[msg.timestamp] = float(msg.altitude)
        elif isinstance(msg, pynmea2.types.talker.RMC) and msg.status == "A" and msg.datestamp and msg.timestamp:
            when = dt.datetime.combine(msg.datestamp, msg.timestamp)
            fixes[_ns(when)] = [msg.latitude, msg.longitude, msg.timestamp]
    rows = [(t, lat, lon, altitude.get(stamp, np.nan)) for t, (lat, lon, stamp) in fixes.items()]
    if not rows:
        raise InputError("no valid RMC sentences (date, time and position) in the NMEA file", path)
    return _track(rows, path)


def _column(header: list[str], names: tuple[str, ...]) -> str | None:
    low = {h.strip().lower(): h for h in header}
    return next((low[n] for n in names if n in low), None)


def _csv_time(text: str) -> int:
    try:
        return round(float(text) * 1e9)
    except ValueError:
        return _ns(dt.datetime.fromisoformat(text.strip().replace("Z", "+00:00")))


def read_csv(path: Path) -> GpsTrack:
    """Rows of a CSV with a header naming lat, lon and time columns (time: ISO 8601 or Unix seconds)."""
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            lat, lon, time, alt = (_column(header, n) for n in (_LAT, _LON, _TIME, _ALT))
            if lat is None or lon is None or time is None:
                raise InputError("GPS CSV needs a header with latitude, longitude and time columns", path)
            rows = [
                (_csv_time(r[time]), float(r[lat]), float(r[lon]), float(r[alt]) if alt and r[alt] else np.nan)
                for r in reader
            ]
    except OSError as e:
        raise InputError(f"cannot read the GPS CSV: {e.strerror}", path) from e
    except (ValueError, TypeError) as e:
        raise InputError(f"GPS CSV has a value that is not a number or a time ({e})", path) from e
    return _track(rows, path)


def read_sidecar(path: Path) -> GpsTrack:
    """The GPS track of a .gpx, .nmea (or .txt/.log of NMEA sentences) or .csv file."""
    if not path.is_file():
        raise InputError("no such GPS file", path)
    suffix = path.suffix.lower()
    if suffix == ".gpx":
        return read_gpx(path)
    if suffix == ".csv":
        return read_csv(path)
    if suffix in (".nmea", ".txt", ".log"):
        return read_nmea(path)
    raise InputError("unknown GPS file type (expected .gpx, .nmea or .csv)", path)


def check_overlap(track: GpsTrack, video_start_ns: int, video_end_ns: int, min_fraction: float = 0.5) -> None:
    """Refuse a track that covers less than `min_fraction` of the video's time span.

    :raises InputError: naming both spans in UTC.
    """
    lo, hi = max(track.t_ns[0], video_start_ns), min(track.t_ns[-1], video_end_ns)
    span = max(video_end_ns - video_start_ns, 1)
    if hi - lo < min_fraction * span:

        def utc(t: int) -> str:
            return dt.datetime.fromtimestamp(t / 1e9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")

        raise InputError(
            f"the GPS track ({utc(track.t_ns[0])} to {utc(track.t_ns[-1])} UTC) does not overlap the video "
            f"({utc(video_start_ns)} to {utc(video_end_ns)} UTC); check --video-start-utc or the GPS file",
            track.path,
        )
