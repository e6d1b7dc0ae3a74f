"""The textured body's two levels for the viewer: a coarse copy of body.glb first, then its full atlas.

body.glb (analysis/body_texture.py) is one glTF binary: the mesh (a few MB) and a JPEG atlas of
up to 8,192 texels a side (15 M of them skin at most). The viewer shows the mesh with a small
atlas first (:func:`preview`: the same glTF with its base colour image scaled down) and then
swaps in the full atlas
(:func:`texture_image`: the image's bytes as stored) with its mipmap chain (:func:`mipmaps`), so
the skin shows long before the atlas has arrived and been decoded, and the browser does not
build the chain itself. Both read the GLB container (glTF 2.0: a 12-byte header, a
JSON chunk and a BIN chunk, every chunk and buffer view 4-byte aligned) and touch nothing but the
image's buffer view; the accessors of the geometry keep their bytes.
"""

from __future__ import annotations

import io
import json
import struct
from typing import Any

import numpy as np
from PIL import Image

from web import images

MAGIC = b"glTF"
JSON_CHUNK = 0x4E4F534A
BIN_CHUNK = 0x004E4942
PREVIEW_PX = 1024
"""The preview atlas' longer side, px (the full one's is up to 8,192)."""
MIP_QUALITY = 90
"""JPEG quality of the mipmap sheet, stored without chroma subsampling: its small levels hold
the whole body in a few hundred texels, where halving the colour's resolution shows."""
MIP_ALIGN = 16
"""Levels start on this grid of the mipmap sheet: a JPEG's 16 x 16 blocks never mix two levels."""


class GlbError(ValueError):
    """A body.glb that is not the glTF binary the viewer needs, naming what is wrong."""


def read_glb(data: bytes) -> tuple[dict[str, Any], bytes]:
    """The JSON document and the BIN chunk of a glTF binary."""
    if len(data) < 20 or data[:4] != MAGIC:
        raise GlbError(f"not a glTF binary (starts {bytes(data[:4])!r}, {len(data)} bytes)")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2 or length != len(data):
        raise GlbError(f"glTF binary version {version}, length {length} in its header for {len(data)} bytes")
    chunks: dict[int, bytes] = {}
    at = 12
    while at + 8 <= len(data):
        size, kind = struct.unpack_from("<II", data, at)
        if at + 8 + size > len(data):
            raise GlbError(f"chunk 0x{kind:08x} of {size} bytes at byte {at} runs past the end")
        chunks.setdefault(kind, data[at + 8: at + 8 + size])
        at += 8 + size
    if JSON_CHUNK not in chunks or BIN_CHUNK not in chunks:
        raise GlbError("a glTF binary with a JSON and a BIN chunk is needed; "
                       f"found chunks {[f'0x{k:08x}' for k in chunks]}")
    try:
        document = json.loads(chunks[JSON_CHUNK])
    except ValueError as exc:
        raise GlbError(f"the JSON chunk does not parse: {exc}") from None
    return document, chunks[BIN_CHUNK]


def _image_index(document: dict[str, Any]) -> int:
    """The image of the first material's base colour texture."""
    try:
        texture = document["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"]
        image = document["textures"][texture]["source"]
        view = document["images"][image]["bufferView"]
        document["bufferViews"][view]
    except (KeyError, IndexError, TypeError):
        raise GlbError("no base colour texture stored in the binary (materials[0] -> textures -> images -> "
                       "bufferView)") from None
    return int(image)


def texture_image(data: bytes) -> tuple[bytes, str]:
    """The base colour image's bytes as stored, and its MIME type."""
    document, blob = read_glb(data)
    return _stored_image(document, blob, _image_index(document))


def with_image(data: bytes, image_bytes: bytes, mime: str) -> bytes:
    """The glTF binary with its base colour image replaced; every other buffer view's bytes unchanged."""
    document, blob = read_glb(data)
    return _replaced(document, blob, _image_index(document), image_bytes, mime)


def preview(data: bytes, longest_px: int = PREVIEW_PX) -> bytes:
    """The glTF binary with its atlas scaled to at most ``longest_px`` a side (JPEG, decoded at
    the JPEG scale that still holds it: web/images.py), the same texture coordinates: what the
    viewer shows while the full atlas comes."""
    document, blob = read_glb(data)
    index = _image_index(document)
    image, _mime = _stored_image(document, blob, index)
    try:
        small = images.scaled(io.BytesIO(image), longest_px)
    except (OSError, Image.DecompressionBombError) as exc:
        raise GlbError(f"the base colour image ({len(image)} bytes) does not decode: {exc}") from None
    return _replaced(document, blob, index, small, "image/jpeg")


def mip_sizes(width: int, height: int) -> list[tuple[int, int]]:
    """(width, height) of mipmap levels 1, 2, ... of a width x height image, down to 1 x 1: each
    side halved and rounded down, never below 1 (OpenGL ES 3.0's chain, which WebGL 2 samples)."""
    sizes = []
    while width > 1 or height > 1:
        width, height = max(1, width // 2), max(1, height // 2)
        sizes.append((width, height))
    return sizes


def mip_layout(width: int, height: int) -> tuple[tuple[int, int], list[tuple[int, int, int, int]]]:
    """The mipmap sheet of a width x height atlas: its (width, height) and where each level lies
    in it, (x, y, width, height) from level 1 on. Level 1 fills the left; the smaller levels stand
    in a column beside it, each starting on the MIP_ALIGN grid."""
    sizes = mip_sizes(width, height)
    if not sizes:  # a 1 x 1 atlas: no level, an empty 1 x 1 sheet (a JPEG has a pixel at least)
        return (1, 1), []
    first_w, first_h = sizes[0]
    column = _aligned(first_w)
    levels = [(0, 0, first_w, first_h)]
    y = 0
    for w, h in sizes[1:]:
        levels.append((column, y, w, h))
        y += _aligned(h)
    sheet_w = column + (sizes[1][0] if len(sizes) > 1 else 0)
    return (max(first_w, sheet_w), max(first_h, y)), levels


def _aligned(px: int) -> int:
    return -(-px // MIP_ALIGN) * MIP_ALIGN


def mipmaps(data: bytes) -> tuple[bytes, list[tuple[int, int, int, int]]]:
    """The atlas' mipmap levels 1, 2, ... down to 1 x 1 on one JPEG sheet (:func:`mip_layout`),
    and where each level lies on it. Level 1 is the atlas decoded at half its JPEG scale (the
    DCT's own low-pass), each further level a box filter of the one before, as a GPU builds its
    chain; the filtering is on the stored sRGB values, which on skin's low contrasts is within a
    JPEG's error of filtering in linear light."""
    document, blob = read_glb(data)
    image_bytes, _mime = _stored_image(document, blob, _image_index(document))
    try:
        with Image.open(io.BytesIO(image_bytes)) as stored:
            width, height = stored.size
            (sheet_w, sheet_h), levels = mip_layout(width, height)
            stored.draft("RGB", levels[0][2:] if levels else (1, 1))
            level = stored.convert("RGB")
    except (OSError, Image.DecompressionBombError) as exc:
        raise GlbError(f"the base colour image ({len(image_bytes)} bytes) does not decode: {exc}") from None
    sheet = Image.new("RGB", (sheet_w, sheet_h))
    for x, y, w, h in levels:
        if level.size != (w, h):
            level = level.resize((w, h), Image.Resampling.BOX)
        # its edges repeated to the block grid: a JPEG block holds the level and no black beside it
        pad = ((0, min(_aligned(h), sheet_h - y) - h), (0, min(_aligned(w), sheet_w - x) - w), (0, 0))
        sheet.paste(Image.fromarray(np.pad(np.asarray(level), pad, mode="edge")), (x, y))
    out = io.BytesIO()
    sheet.save(out, format="JPEG", quality=MIP_QUALITY, subsampling=0)
    return out.getvalue(), levels


def _stored_image(document: dict[str, Any], blob: bytes, index: int) -> tuple[bytes, str]:
    image = document["images"][index]
    view = document["bufferViews"][image["bufferView"]]
    start = int(view.get("byteOffset", 0))
    end = start + int(view["byteLength"])
    if end > len(blob):
        raise GlbError(f"the image's buffer view ends at byte {end} of a {len(blob)}-byte BIN chunk")
    return blob[start:end], str(image.get("mimeType", "image/jpeg"))


def _replaced(document: dict[str, Any], blob: bytes, index: int, image_bytes: bytes, mime: str) -> bytes:
    """The GLB of ``document`` and ``blob`` with image ``index``'s bytes replaced, the buffer views
    laid out again in their order, each 4-byte aligned."""
    target = document["images"][index]["bufferView"]
    views = document["bufferViews"]
    out = bytearray()
    for i in sorted(range(len(views)), key=lambda i: int(views[i].get("byteOffset", 0))):
        view = views[i]
        start = int(view.get("byteOffset", 0))
        part = image_bytes if i == target else blob[start: start + int(view["byteLength"])]
        out += b"\0" * (-len(out) % 4)
        view["byteOffset"] = len(out)
        view["byteLength"] = len(part)
        out += part
    out += b"\0" * (-len(out) % 4)
    document["images"][index]["mimeType"] = mime
    document["buffers"][0]["byteLength"] = len(out)
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), JSON_CHUNK) + text + struct.pack("<II", len(out), BIN_CHUNK) + bytes(out)
    return MAGIC + struct.pack("<II", 2, 12 + len(body)) + body
