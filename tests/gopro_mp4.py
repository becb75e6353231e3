"""Test helper: a GoPro-style MP4, i.e. an MP4 video with a GPMF telemetry track ("GoPro MET", sample entry `gpmd`)
whose one-second samples carry GPS5 fixes (lat, lon, alt, 2D and 3D speed, scaled int32) and their GPSU UTC time,
laid out as GoPro cameras write them (github.com/gopro/gpmf-parser, docs/README.md: KLV records of a FourCC key, a
type character, a structure size and a repeat count, padded to 4 bytes; DEVC > STRM > STNM, GPSF, GPSU, SCAL, GPS5).

The video is written by OpenCV (its `moov` box last); the telemetry track is added to that `moov` and its samples
appended in a second `mdat` after it. Real GoPro files are not in ../shared, and no small one is redistributable here.
"""

from __future__ import annotations

import datetime as dt
import struct
from pathlib import Path

import numpy as np

GPS_SCALE = (10_000_000, 10_000_000, 1000, 1000, 100)  # GoPro's SCAL for GPS5: deg, deg, m, m/s, m/s
_GPS_NAME = b"GPS (Lat., Long., Alt., 2D speed, 3D speed)"


def _klv(key: bytes, kind: bytes, size: int, repeat: int, data: bytes) -> bytes:
    """One GPMF record, its data padded to 4 bytes."""
    return key + kind + struct.pack(">BH", size, repeat) + data + b"\0" * (-len(data) % 4)


def _nested(key: bytes, children: bytes) -> bytes:
    return _klv(key, b"\0", 1, len(children), children)


def gpmf_payload(utc: dt.datetime, fixes: np.ndarray, fix_type: int = 3) -> bytes:
    """One second of GoPro GPS telemetry: `fixes` (n, 5) lat deg, lon deg, alt m, speed 2D and 3D m/s; the first
    fix at `utc`; `fix_type` is GPSF (0 no fix, 2 2D, 3 3D)."""
    stamp = utc.strftime("%y%m%d%H%M%S.") + f"{utc.microsecond // 1000:03d}"
    scaled = np.round(fixes * np.asarray(GPS_SCALE, float)).astype(">i4")
    stream = b"".join(
        [
            _klv(b"STNM", b"c", 1, len(_GPS_NAME), _GPS_NAME),
            _klv(b"GPSF", b"L", 4, 1, struct.pack(">I", fix_type)),
            _klv(b"GPSU", b"U", 16, 1, stamp.encode()),
            _klv(b"GPSP", b"S", 2, 1, struct.pack(">H", 150)),
            _klv(b"SCAL", b"l", 4, 5, struct.pack(">5i", *GPS_SCALE)),
            _klv(b"GPS5", b"l", 20, len(scaled), scaled.tobytes()),
        ]
    )
    device = _klv(b"DVID", b"L", 4, 1, struct.pack(">I", 1)) + _klv(b"DVNM", b"c", 1, 11, b"HERO9 Black")
    return _nested(b"DEVC", device + _nested(b"STRM", stream))


def _box(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", 8 + len(payload)) + kind + payload


def _full_box(kind: bytes, payload: bytes, flags: int = 0) -> bytes:
    return _box(kind, struct.pack(">I", flags) + payload)


def _telemetry_trak(track_id: int, sizes: list[int], first_offset: int, timescale: int, duration: int) -> bytes:
    """A `trak` of len(sizes) one-second GPMF samples stored one after the other from `first_offset`."""
    matrix = struct.pack(">9i", 0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000)
    header = struct.pack(">IIIII8xhhhh", 0, 0, track_id, 0, duration, 0, 0, 0, 0)
    tkhd = _full_box(b"tkhd", header + matrix + b"\0" * 8, 3)
    mdhd = _full_box(b"mdhd", struct.pack(">IIIIHH", 0, 0, timescale, duration, 0x55C4, 0))
    hdlr = _full_box(b"hdlr", struct.pack(">I", 0) + b"meta" + b"\0" * 12 + b"\tGoPro MET\0")
    dinf = _box(b"dinf", _full_box(b"dref", struct.pack(">I", 1) + _full_box(b"url ", b"", 1)))
    offsets = first_offset + np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)
    stbl = _box(
        b"stbl",
        _full_box(b"stsd", struct.pack(">I", 1) + _box(b"gpmd", b"\0" * 6 + struct.pack(">H", 1) + b"\0" * 4))
        + _full_box(b"stts", struct.pack(">III", 1, len(sizes), timescale))
        + _full_box(b"stsc", struct.pack(">IIII", 1, 1, 1, 1))
        + _full_box(b"stsz", struct.pack(">II", 0, len(sizes)) + struct.pack(f">{len(sizes)}I", *sizes))
        + _full_box(b"stco", struct.pack(">I", len(sizes)) + struct.pack(f">{len(sizes)}I", *offsets)),
    )
    minf = _box(b"minf", _full_box(b"nmhd", b"") + dinf + stbl)
    return _box(b"trak", tkhd + _box(b"mdia", mdhd + hdlr + minf))


def _top_boxes(data: bytes) -> list[tuple[bytes, int, int]]:
    """(kind, start, end) of the file's top-level boxes."""
    boxes, pos = [], 0
    while pos < len(data):
        size, kind = struct.unpack(">I4s", data[pos : pos + 8])
        boxes.append((kind, pos, pos + size))
        pos += size
    return boxes


def add_gopro_gps(video: Path, payloads: list[bytes]) -> None:
    """Add a GPMF track of one-second `payloads` to an OpenCV-written MP4 (in place)."""
    data = video.read_bytes()
    boxes = _top_boxes(data)
    kind, start, end = boxes[-1]
    if kind != b"moov":
        raise ValueError(f"{video}: expected the moov box last, got {[b[0] for b in boxes]}")
    moov_children = data[start + 8 : end]
    timescale = 1000
    sizes = [len(p) for p in payloads]
    trak_len = len(_telemetry_trak(99, sizes, 0, timescale, timescale * len(payloads)))
    first_offset = start + 8 + len(moov_children) + trak_len + 8  # after the new moov and the new mdat's header
    trak = _telemetry_trak(99, sizes, first_offset, timescale, timescale * len(payloads))
    video.write_bytes(data[:start] + _box(b"moov", moov_children + trak) + _box(b"mdat", b"".join(payloads)))
