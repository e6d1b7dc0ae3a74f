"""Printable pictures of the calibration cuboid's boards: one PNG and one true-size PDF per face."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from planner.calibration.target import CuboidTarget

MM_PER_INCH = 25.4


def write_target_prints(target: CuboidTarget, out: Path) -> list[Path]:
    """Write ``face_<name>.png`` and ``face_<name>.pdf`` for every face into ``out`` (created); returns the files.

    The pictures are at the target's ``print_dpi``; the PDF page is the board's true size (print at
    100 %, no "fit to page"), the PNG carries the same resolution so image tools print it true to size.
    """
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    px_per_mm = target.print_dpi / MM_PER_INCH
    files = []
    for face in target.faces:
        image = Image.fromarray(np.ascontiguousarray(target.board_image(face.index, px_per_mm)), "L")
        stem = "face_" + face.name.replace("+", "plus_").replace("-", "minus_")
        png, pdf = out / f"{stem}.png", out / f"{stem}.pdf"
        image.save(png, dpi=(target.print_dpi, target.print_dpi))
        image.save(pdf, "PDF", resolution=float(target.print_dpi),
                   title=f"{target.name} face {face.name}: markers {face.first_marker_id}.."
                         f"{face.first_marker_id + target.markers_per_face - 1}, squares {target.square_mm:g} mm")
        files += [png, pdf]
    return files
