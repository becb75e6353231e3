"""The stamps of a sensor series put in order before it is written, or the series refused when they cannot time it.

A series is written sorted by time, because several publishers on one topic may interleave and a driver's stamps may
jitter. For a stream whose samples are places (GPS fixes, odometry and ground-truth poses, /tf vehicle poses)
sorting hides a broken clock: shuffled stamps reorder the positions into a zig-zag that is longer than the drive
and turns at every sample. So for those streams:
- stamps that go back in time in the recording's own order are sorted when they are a few (at most
  MAX_BROKEN_FRACTION of the samples: jitter, interleaving) and refused when they are more;
- samples sharing a stamp keep one: identical repeats (a message recorded twice) silently; for poses that are
  interpolated as they are (odometry, ground truth, /tf), different values at one instant (a clock that did not
  advance) are refused past the same fraction, the first kept below it.
GPS fixes sharing a stamp keep the first without a refusal (receivers that stamp in whole seconds do this, and the
fusion weighs each fix by its covariance); rate streams (IMU, speed) are sorted and keep the first of a stamp without
a refusal: their order does not move the path.
"""

from __future__ import annotations

import numpy as np

from drivesim.pipeline.errors import InputError

MAX_BROKEN_FRACTION = 0.01
"""Share of a position stream's samples whose stamps may go back in time or repeat with other values."""
POSITION_STREAMS = ("gps", "odometry", "ground_truth", "/tf vehicle poses")
"""Streams whose samples are places, so their order is the path's shape."""
POSE_STREAMS = ("odometry", "ground_truth", "/tf vehicle poses")
"""Position streams whose samples become the path as they are, so one instant must have one pose."""


def _too_many(count: int, total: int) -> bool:
    return count > MAX_BROKEN_FRACTION * total


def ordered_series(arrays: dict[str, np.ndarray], stream: str) -> dict[str, np.ndarray]:
    """The columns of one series (t_ns among them) sorted by time with one sample per stamp.

    :param stream: its name ("odometry", "gps", ...), which says whether it is a position stream.
    :raises InputError: a position stream whose stamps go back in time, or a pose stream (POSE_STREAMS) whose stamps
        repeat with other values, at more than MAX_BROKEN_FRACTION of its samples.
    """
    t_ns = np.asarray(arrays["t_ns"], dtype=np.int64)
    n = len(t_ns)
    positional = stream in POSITION_STREAMS
    backwards = np.flatnonzero(np.diff(t_ns) < 0)
    if positional and _too_many(len(backwards), n):
        raise InputError(
            f"the {stream} stamps go back in time at {len(backwards)} of {n} samples (first at sample "
            f"{int(backwards[0]) + 2}): they do not time these positions, and sorted they would draw a zig-zag; "
            "fix the recording's stamps"
        )
    order = np.argsort(t_ns, kind="stable")
    if len(backwards):
        arrays = {name: np.asarray(a)[order] for name, a in arrays.items()}
        t_ns = t_ns[order]
    repeat = np.flatnonzero(np.diff(t_ns) == 0) + 1  # each sample that repeats its predecessor's stamp
    if not len(repeat):
        return arrays
    conflicting = [i for i in repeat if not _same_row(arrays, i - 1, i)]
    if stream in POSE_STREAMS and _too_many(len(conflicting), n):
        raise InputError(
            f"{len(conflicting)} of {n} {stream} samples share their stamp with another of different values "
            f"(first at sample {int(conflicting[0]) + 1}): a clock that does not advance cannot time a drive; fix "
            "the recording's stamps"
        )
    keep = np.ones(n, dtype=bool)
    keep[repeat] = False
    return {name: np.asarray(a)[keep] for name, a in arrays.items()}


def _same_row(arrays: dict[str, np.ndarray], i: int, j: int) -> bool:
    return all(np.asarray(a[i]).tobytes() == np.asarray(a[j]).tobytes() for a in arrays.values())
