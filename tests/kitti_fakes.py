"""Small KITTI-layout folders the ingest tests write themselves (no shared data needed)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from recordings import textured_image

FX_PX = 80.0


def kitti_stereo_folder(
    folder: Path,
    n: int = 5,
    width: int = 96,
    height: int = 32,
    baseline_m: float = 0.5,
    names: tuple[str, str] = ("image_l", "image_r"),
) -> Path:
    """A small KITTI odometry stereo folder: image_l/, image_r/ (textured grey PNGs, `names`), calib.txt (P0, P1:
    the right camera `baseline_m` to the right at fx 80 px), poses.txt (1 m forward per frame), no times.txt."""
    folder.mkdir(parents=True, exist_ok=True)
    for side, seed in zip(names, (0, 1), strict=True):
        (folder / side).mkdir(exist_ok=True)
        for i in range(n):
            grey = cv2.cvtColor(textured_image(width, height, i, seed=seed), cv2.COLOR_RGB2GRAY)
            cv2.imwrite(str(folder / side / f"{i:06d}.png"), grey)
    fx, cx, cy = FX_PX, (width - 1) / 2, (height - 1) / 2
    P0 = np.array([[fx, 0, cx, 0], [0, fx, cy, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -fx * baseline_m
    (folder / "calib.txt").write_text(
        "".join(f"P{k}: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n" for k, P in enumerate((P0, P1)))
    )
    poses = np.tile(np.eye(4)[:3], (n, 1, 1))
    poses[:, 2, 3] = np.arange(n, dtype=float)
    np.savetxt(folder / "poses.txt", poses.reshape(n, 12), fmt="%.6e")
    return folder
