"""Image previews for the browser: thumbnails, screen-sized previews and zoomed crops.

Phone images are large JPEGs (the rig's 8192 x 6144 sensor); the browser gets what it shows.
JPEG draft mode decodes at 1/2..1/8 scale straight from the DCT, so a thumbnail costs a few
milliseconds instead of a full decode.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import IO

from PIL import Image, ImageDraw

THUMB_PX = 160
PREVIEW_PX = 1200
CROP_OUT_PX = 320


class ImageRequestError(ValueError):
    """A preview request names an impossible size or crop."""


class ImageUnreadable(OSError):
    """A stored picture does not decode (cut short or damaged on disk); an OSError, as PIL's own
    are, for the callers that catch those (web/glb.py's preview)."""


#: What PIL raises for a file that is not a whole picture.
_UNDECODABLE = (OSError, ValueError, SyntaxError, Image.DecompressionBombError)


def _encode(image: Image.Image) -> bytes:
    out = io.BytesIO()
    image.convert("RGB").save(out, format="JPEG", quality=88)
    return out.getvalue()


def scaled(source: Path | IO[bytes], max_px: int) -> bytes:
    """JPEG of the image (a file, or its bytes in a file object) fitted into max_px x max_px
    (never enlarged)."""
    try:
        with Image.open(source) as image:
            image.draft("RGB", (max_px, max_px))
            image = image.convert("RGB")
            image.thumbnail((max_px, max_px))
    except _UNDECODABLE as exc:
        raise ImageUnreadable(f"{_name(source)} does not decode: {exc}") from exc
    return _encode(image)


def crop(path: Path, u_px: float, v_px: float, full_width_px: int, half_px: float,
         out_px: int = CROP_OUT_PX) -> bytes:
    """A square crop centred on the full-resolution pixel (u, v), ``half_px`` full-resolution
    pixels each side, enlarged or reduced to out_px, with the spot ringed.

    The stored image may be smaller than the sensor (the simulator renders at 1/32): pixel
    coordinates are scaled by the image's width over ``full_width_px``.
    """
    if not half_px > 0 or not full_width_px > 0:
        raise ImageRequestError(f"crop half-size {half_px!r} px and width {full_width_px!r} px must be positive")
    try:
        with Image.open(path) as image:
            scale = image.width / full_width_px
            u, v, half = u_px * scale, v_px * scale, max(half_px * scale, 2.0)
            box = (round(u - half), round(v - half), round(u + half), round(v + half))
            part = image.convert("RGB").crop(box)
    except _UNDECODABLE as exc:
        raise ImageUnreadable(f"{_name(path)} does not decode: {exc}") from exc
    part = part.resize((out_px, out_px), Image.Resampling.LANCZOS if scale >= 1 else Image.Resampling.BICUBIC)
    draw = ImageDraw.Draw(part)
    ring = out_px * 0.06
    c = out_px / 2
    draw.ellipse((c - ring, c - ring, c + ring, c + ring), outline=(0, 220, 255), width=2)
    return _encode(part)


def _name(source: Path | IO[bytes]) -> str:
    return source.name if isinstance(source, Path) else "the image"
