"""The textured body's two levels for the viewer (web/glb.py): the preview glTF and the full atlas."""

from __future__ import annotations

import io
import struct
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from analysis.body_texture import glb_bytes
from web.glb import MIP_ALIGN, GlbError, mip_layout, mip_sizes, mipmaps, preview, read_glb, texture_image, with_image


def _body(width: int, height: int, seed: int = 0) -> bytes:
    """body.glb as analysis/body_texture.py writes it, for a box whose atlas is a smooth random image."""
    rng = np.random.default_rng(seed)
    box = trimesh.creation.box(extents=(300.0, 200.0, 1000.0))
    small = rng.integers(40, 230, (8, 8, 3)).astype(np.uint8)
    texture = np.asarray(Image.fromarray(small).resize((width, height), Image.BILINEAR))
    atlas = SimpleNamespace(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces),
                            uv=rng.uniform(0.05, 0.95, (len(box.vertices), 2)))
    return glb_bytes(SimpleNamespace(texture=texture, atlas=atlas))  # type: ignore[arg-type]


def _mesh(data: bytes) -> trimesh.Trimesh:
    return next(iter(trimesh.load(io.BytesIO(data), file_type="glb").geometry.values()))


def _views(data: bytes) -> list[bytes]:
    document, blob = read_glb(data)
    return [blob[v.get("byteOffset", 0): v.get("byteOffset", 0) + v["byteLength"]] for v in document["bufferViews"]]


def test_the_full_atlas_is_the_stored_jpeg() -> None:
    data = _body(700, 500)
    image, mime = texture_image(data)
    assert mime == "image/jpeg" and image[:3] == b"\xff\xd8\xff"
    stored = _mesh(data).visual.material.baseColorTexture
    assert Image.open(io.BytesIO(image)).size == stored.size == (700, 500)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(image)).convert("RGB")), np.asarray(stored.convert("RGB")))


@pytest.mark.parametrize("size", [(3000, 2000), (1500, 2600), (640, 480)])
def test_the_preview_is_the_same_mesh_with_the_atlas_scaled_to_at_most_the_preview_size(size) -> None:
    data = _body(*size)
    small = preview(data, 1024)
    full, coarse = _mesh(data), _mesh(small)
    assert np.array_equal(full.vertices, coarse.vertices) and np.array_equal(full.faces, coarse.faces)
    assert np.array_equal(full.visual.uv, coarse.visual.uv)
    texture = coarse.visual.material.baseColorTexture
    scale = min(1.0, 1024 / max(size))
    assert texture.size == (round(size[0] * scale), round(size[1] * scale))
    # the same picture, smaller: the full atlas scaled alike differs by a few grey levels at most
    expected = np.asarray(full.visual.material.baseColorTexture.convert("RGB").resize(texture.size, Image.BOX), float)
    assert np.abs(np.asarray(texture.convert("RGB"), float) - expected).mean() < 3.0
    assert len(texture_image(small)[0]) < len(texture_image(data)[0]) or scale == 1.0


@given(st.binary(min_size=0, max_size=64), st.sampled_from(["image/jpeg", "image/png"]))
def test_replacing_the_image_keeps_every_other_buffer_view_and_a_valid_container(image: bytes, mime: str) -> None:
    data = _body(64, 48)
    document, _ = read_glb(data)
    target = document["images"][0]["bufferView"]
    out = with_image(data, image, mime)
    assert texture_image(out) == (image, mime)
    before, after = _views(data), _views(out)
    assert [b for i, b in enumerate(before) if i != target] == [b for i, b in enumerate(after) if i != target]
    assert struct.unpack_from("<I", out, 8)[0] == len(out) and len(out) % 4 == 0
    new, blob = read_glb(out)
    assert all(v["byteOffset"] % 4 == 0 for v in new["bufferViews"]) and new["buffers"][0]["byteLength"] == len(blob)


def test_a_body_that_is_not_a_textured_gltf_binary_is_named() -> None:
    with pytest.raises(GlbError, match="not a glTF binary"):
        texture_image(b"PK\x03\x04" + bytes(40))
    data = _body(64, 48)
    with pytest.raises(GlbError, match="runs past the end"):
        texture_image(data[:12] + struct.pack("<II", 10**6, 0x4E4F534A) + data[20:])
    bare = trimesh.Scene(trimesh.creation.box()).export(file_type="glb")
    with pytest.raises(GlbError, match="no base colour texture"):
        preview(bare)
    with pytest.raises(GlbError, match="does not decode"):
        preview(with_image(data, b"not a jpeg", "image/jpeg"))


@given(st.integers(1, 20_000), st.integers(1, 20_000))
def test_the_mipmap_chain_halves_each_side_down_to_one_texel(width: int, height: int) -> None:
    sizes = mip_sizes(width, height)
    assert len(sizes) == max(width, height).bit_length() - 1  # WebGL's floor(log2(max side)) levels after 0
    previous = (width, height)
    for size in sizes:
        assert size == (max(1, previous[0] // 2), max(1, previous[1] // 2))
        previous = size
    assert not sizes or sizes[-1] == (1, 1)


@given(st.integers(1, 20_000), st.integers(1, 20_000))
def test_the_mipmap_levels_lie_apart_on_the_sheet_each_on_the_jpeg_block_grid(width: int, height: int) -> None:
    (sheet_w, sheet_h), levels = mip_layout(width, height)
    assert [(w, h) for _, _, w, h in levels] == mip_sizes(width, height)
    for i, (x, y, w, h) in enumerate(levels):
        assert x % MIP_ALIGN == 0 and y % MIP_ALIGN == 0 and x + w <= sheet_w and y + h <= sheet_h
        for x2, y2, w2, h2 in levels[:i]:  # blocks apart: a 16 x 16 JPEG block holds one level at most
            rounded = (-(-w // MIP_ALIGN) * MIP_ALIGN, -(-h // MIP_ALIGN) * MIP_ALIGN)
            rounded2 = (-(-w2 // MIP_ALIGN) * MIP_ALIGN, -(-h2 // MIP_ALIGN) * MIP_ALIGN)
            assert x + rounded[0] <= x2 or x2 + rounded2[0] <= x or y + rounded[1] <= y2 or y2 + rounded2[1] <= y
    # about three eighths of the atlas' area: level 1 and a column a quarter of the atlas wide
    assert sheet_w < width // 2 + max(1, width // 4) + MIP_ALIGN and sheet_h <= max(1, height // 2 + MIP_ALIGN * len(levels))


@pytest.mark.parametrize("size", [(1200, 800), (333, 1025), (1, 1), (1, 3)])
def test_the_mipmap_levels_are_the_atlas_box_filtered(size) -> None:
    data = _body(*size)
    sheet, levels = mipmaps(data)
    assert levels == mip_layout(*size)[1]
    picture = Image.open(io.BytesIO(sheet)).convert("RGB")
    assert picture.size == mip_layout(*size)[0]
    expected = Image.open(io.BytesIO(texture_image(data)[0])).convert("RGB")
    for x, y, w, h in levels:  # each the one before box-filtered, as a GPU builds the chain
        expected = expected.resize((w, h), Image.BOX)
        error = np.abs(np.asarray(picture.crop((x, y, x + w, y + h)), float) - np.asarray(expected, float)).mean()
        # a few grey levels of JPEG error; more in levels smaller than a block, where this atlas'
        # random colours (far busier than skin) change every texel or two
        assert error < (3.0 if min(w, h) >= MIP_ALIGN else 8.0), (w, h, error)
    with pytest.raises(GlbError, match="does not decode"):
        mipmaps(with_image(data, b"not a jpeg", "image/jpeg"))
