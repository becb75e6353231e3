"""Probe: does a rounder or more tapered library car move the C2ST?

The default crops of `what_separates.py`, then the same boxes with the procedural library rebuilt from shapes changed
one way at a time (the vehicle builder's section and glass-house functions wrapped, nothing else): the hull's
cross-section corners rounder (radius x 2.5, six points per corner), the glass house and roof narrower at the top
(x 0.85), both, and both pushed further (x 4, x 0.7). Prints each accuracy.

    .venv/bin/python experiments/car_look/shape_probe.py   # ~5 min
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import what_separates as ws  # noqa: E402

from drivesim.sim import vehicles  # noqa: E402

cr = ws.cr


@contextmanager
def wrapped(name: str, make: Callable[[Callable], Callable]) -> Iterator[None]:
    """`vehicles.<name>` replaced by `make(original)` for the block."""
    original = getattr(vehicles, name)
    setattr(vehicles, name, make(original))
    try:
        yield
    finally:
        setattr(vehicles, name, original)


def rounder(factor: float) -> Callable[[Callable], Callable]:
    """The hull's section corners `factor` times rounder, six points per corner."""

    def make(original: Callable) -> Callable:
        def section(half_w, top_half_w, z_bottom, z_top, radius, arc):
            return original(half_w, top_half_w, z_bottom, z_top, factor * radius, max(arc, 6))

        return section

    return make


def narrower_top(factor: float) -> Callable[[Callable], Callable]:
    """A part's vertices at the roof's height and above `factor` times as far from the centre line."""

    def make(original: Callable) -> Callable:
        def part(shape, lay):
            vertices, faces = original(shape, lay)
            top = vertices[:, 2] >= lay.roof_z - 1e-6
            vertices = vertices.copy()
            vertices[top, 1] *= factor
            return vertices, faces

        return part

    return make


def crops(boxes: list) -> np.ndarray:
    """Inserted crops of every box with the library as the vehicle builder makes it now."""
    return np.stack([ws.scene_of(i, b).shipped for i, b in enumerate(boxes)])


def main() -> int:
    boxes = cr.load_boxes(ws.BOXES)
    real = np.stack([ws.scene_of(i, b).real for i, b in enumerate(boxes)])
    variants: dict[str, list[tuple[str, Callable]]] = {
        "as shipped": [],
        "rounder hull sections (x2.5)": [("_rounded_section", rounder(2.5))],
        "narrower glass house and roof top (x0.85)": [
            ("_glass_house", narrower_top(0.85)),
            ("_roof", narrower_top(0.85)),
        ],
        "both": [
            ("_rounded_section", rounder(2.5)),
            ("_glass_house", narrower_top(0.85)),
            ("_roof", narrower_top(0.85)),
        ],
        "rounder x4, narrower x0.7": [
            ("_rounded_section", rounder(4.0)),
            ("_glass_house", narrower_top(0.7)),
            ("_roof", narrower_top(0.7)),
        ],
    }
    for name, patches in variants.items():
        with ExitStack() as stack:
            for name_of_part, make in patches:
                stack.enter_context(wrapped(name_of_part, make))
            inserted = crops(boxes)
        acc, low, high = cr.accuracy_interval(ws.accuracy(real, inserted)[None])
        print(f"{name}: {100 * acc:.0f} % [{100 * low:.0f}, {100 * high:.0f}]", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
