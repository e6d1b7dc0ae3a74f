"""The textured body in the viewer, in real headless Chromium (software WebGL)."""

from __future__ import annotations

import io
import json
import os
import shutil
from pathlib import Path
from urllib.error import HTTPError
from urllib.request import urlopen

import numpy as np
import pytest
from PIL import Image
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.actions.wheel_input import ScrollOrigin

from analysis.body_texture import write_body
from analysis.scan_views import open_scan
from cli import main
from tests.bench.texture import delta_e00, srgb_to_lab
from tests.test_web import folder_of
from tests.test_web_browser import front_vertex
from tests.web_browser import canvas_is_blank, chromium, chromium_missing, click_at, serve_in_thread, wait_for
from web.glb import PREVIEW_PX, mip_layout, mip_sizes, texture_image

pytestmark = pytest.mark.skipif(chromium_missing() is not None, reason=str(chromium_missing()))
SHOTS = Path(os.environ.get("TBP_SCREENSHOTS", "/tmp/tbp-web-screenshots"))


def _green_share(png: bytes) -> float:
    """Share of the drawn pixels that are the QA map's green (sharp skin)."""
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float).reshape(-1, 3)
    drawn = pixels[np.abs(pixels - [28, 36, 49]).max(axis=1) > 12]  # not the stage's background
    green = (drawn[:, 1] > drawn[:, 0] + 20) & (drawn[:, 1] > drawn[:, 2] + 10)
    return float(green.mean()) if len(drawn) else 0.0


def _skin_colour(png: bytes) -> np.ndarray:
    """Median RGB of the drawn pixels (the body's outline, blended with the background, is a minority)."""
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float).reshape(-1, 3)
    return np.median(pixels[np.abs(pixels - [28, 36, 49]).max(axis=1) > 12], axis=0)


def _zoomed_out(driver) -> bytes:  # noqa: ANN001
    canvas = driver.find_element("css selector", "canvas")
    ActionChains(driver).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, 2000).perform()
    driver.execute_script("return new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    return canvas.screenshot_as_png


def test_the_viewer_shows_the_skin_and_the_sharpness_map_one_click_away(web_store, tmp_path, capsys):
    name = folder_of(web_store)
    store = tmp_path / "store"
    shutil.copytree(web_store / name, store / name)
    scan_dir = store / name
    write_body(scan_dir, texel_mm=3.0)
    vertex = front_vertex(scan_dir)
    SHOTS.mkdir(parents=True, exist_ok=True)
    with serve_in_thread(store) as url, chromium() as driver:
        driver.get(f"{url}/scans/{name}")
        assert wait_for(driver, "window.tbpViewer && (window.tbpViewer.ready || window.tbpViewer.error)") is True
        wait_for(driver, "window.tbpViewer.shown === 'texture' || window.tbpViewer.error")
        assert driver.execute_script("return window.tbpViewer.error") is None
        driver.execute_script("return new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
        canvas = driver.find_element("css selector", "canvas")
        skin = canvas.screenshot_as_png
        driver.save_screenshot(str(SHOTS / "viewer-textured.png"))
        assert not canvas_is_blank(skin)
        assert _green_share(skin) < 0.05  # skin, not the QA map's green

        toggle = driver.find_element("id", "body-toggle")
        toggle.click()
        wait_for(driver, "window.tbpViewer.shown === 'sharpness'")
        driver.execute_script("return new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
        assert _green_share(canvas.screenshot_as_png) > 0.3
        toggle.click()
        wait_for(driver, "window.tbpViewer.shown === 'texture'")

        # a click on the textured skin finds the image tbp navigate gives for that spot
        where = open_scan(scan_dir).mesh().vertices[vertex].tolist()
        spot = driver.execute_script("return window.tbpViewer.project(arguments[0])", where)
        click_at(driver, spot["x"], spot["y"])
        wait_for(driver, "document.querySelector('#best-image')")
        best = driver.find_element("id", "best-image")
        point = json.loads(driver.find_element("id", "spot-point").get_attribute("data-point"))
        assert np.linalg.norm(np.array(point) - where) < 5.0
        capsys.readouterr()
        assert main(["navigate", str(scan_dir), "--point", ",".join(map(repr, point)), "--json"]) == 0
        assert best.get_attribute("data-file") == json.loads(capsys.readouterr().out)["views"][0]["file"]

        # the preview atlas came first; the full atlas replaced it, texel for texel the stored one
        wait_for(driver, "window.tbpViewer.textureLevel === 'full' || window.tbpViewer.error")
        assert driver.execute_script("return window.tbpViewer.error") is None
        timing = driver.execute_script("return window.tbpViewer.timing")
        assert timing["bodyBuiltMs"] < timing["fullTextureMs"]
        stored = Image.open(io.BytesIO(texture_image((scan_dir / "body.glb").read_bytes())[0]))
        size = driver.execute_script("return window.tbpViewer.textureSize")
        assert (size["width"], size["height"]) == stored.size
        # uploaded with its whole mipmap chain, which the browser did not have to build
        assert driver.execute_script("return window.tbpViewer.textureMipmaps") == [list(stored.size)] + [
            list(s) for s in mip_sizes(*stored.size)]
        driver.execute_script("return new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
        detailed = canvas.screenshot_as_png
        assert _green_share(detailed) < 0.05
        print(f"first paint {driver.execute_script('return window.tbpViewer.firstPaintMs'):.0f} ms, "
              f"textured body built {timing['bodyBuiltMs']:.0f} ms, full texture {timing['fullTextureMs']:.0f} ms")
        # zoomed out, the body samples the atlas' smaller mipmap levels: the skin the browser's own
        # chain of the preview atlas shows there (a page whose full atlas never comes)
        far = _zoomed_out(driver)
        driver.execute_cdp_cmd("Network.enable", {})
        driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": ["*/body/texture*"]})
        driver.get(f"{url}/scans/{name}")
        wait_for(driver, "window.tbpViewer && window.tbpViewer.textureLevel === 'preview' && window.tbpViewer.error")
        reference = _zoomed_out(driver)
        driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": []})
        # the two chains filter differently (the server's box filter on the stored sRGB values, the
        # browser's as its GPU makes them, from a smaller atlas): over this coarse atlas's many chart
        # borders they differ by 3-4.5 CIEDE2000; a black or misplaced level differs by tens
        lab = srgb_to_lab(np.array([_skin_colour(far), _skin_colour(reference)]))
        difference = float(delta_e00(lab[:1], lab[1:])[0])
        assert difference < 5.0, (_skin_colour(far), _skin_colour(reference), difference)

        # the two levels over HTTP: a smaller atlas in the same glTF, and the stored atlas itself
        glb = urlopen(f"{url}/api/scans/{name}/body?texture=preview").read()
        coarse = Image.open(io.BytesIO(texture_image(glb)[0]))
        assert max(coarse.size) == min(PREVIEW_PX, max(stored.size))
        full = urlopen(f"{url}/api/scans/{name}/body/texture")
        assert full.headers["Content-Type"] == "image/jpeg"
        assert full.read() == texture_image((scan_dir / "body.glb").read_bytes())[0]
        mips = urlopen(f"{url}/api/scans/{name}/body/texture/mipmaps")
        levels = json.loads(mips.headers["Tbp-Mipmap-Levels"])
        assert mips.headers["Content-Type"] == "image/jpeg" and levels == [list(x) for x in mip_layout(*stored.size)[1]]
        assert Image.open(io.BytesIO(mips.read())).size == mip_layout(*stored.size)[0]
        with pytest.raises(HTTPError) as refused:
            urlopen(f"{url}/api/scans/{name}/body?texture=huge")
        assert refused.value.code == 400 and "full or preview" in json.loads(refused.value.read())["error"]["message"]


def test_a_body_glb_that_is_not_a_textured_gltf_is_named_on_the_page(web_store, tmp_path):
    """The viewer keeps the QA map and says what is wrong with the body; the server names the file."""
    name = folder_of(web_store)
    store = tmp_path / "store"
    shutil.copytree(web_store / name, store / name)
    write_body(store / name, texel_mm=6.0)
    (store / name / "body.glb").write_bytes(b"PK\x03\x04 a zip file, not glTF")
    with serve_in_thread(store) as url, chromium() as driver:
        for path in ("body?texture=preview", "body/texture", "body/texture/mipmaps"):
            with pytest.raises(HTTPError) as refused:
                urlopen(f"{url}/api/scans/{name}/{path}")
            message = json.loads(refused.value.read())["error"]["message"]
            assert refused.value.code == 422 and message.startswith("body.glb: not a glTF binary"), message
        driver.get(f"{url}/scans/{name}")
        wait_for(driver, "window.tbpViewer && window.tbpViewer.ready && window.tbpViewer.error")
        assert "not a glTF binary" in driver.find_element("id", "stage-msg").text
        assert driver.execute_script("return window.tbpViewer.shown") == "sharpness"
