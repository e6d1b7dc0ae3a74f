"""The simulated phone's pictures (thin-lens defocus) and its standalone adbd server."""

from __future__ import annotations

import io
import signal
import subprocess
import sys

import numpy as np
import pytest
import trimesh
from PIL import Image

from drivers.sim.phone import SimulatedPhone
from drivers.sim.phone_render import PhoneRenderer, SubjectScene, circle_of_confusion_mm, empty_rig_picture, encode_jpeg
from planner.rig import load_rig

DEFAULT_OPTICS = load_rig().optics


def test_circle_of_confusion_is_zero_at_focus_and_grows_away() -> None:
    z = np.array([200.0, 300.0, 400.0, 600.0, 2000.0])
    coc = circle_of_confusion_mm(z, 400.0, DEFAULT_OPTICS)
    assert coc[2] == 0.0
    assert coc[0] > coc[1] > 0 and 0 < coc[3] < coc[4]
    f, n = DEFAULT_OPTICS.focal_length_mm, DEFAULT_OPTICS.f_number
    assert coc[0] == pytest.approx((f / n) * 200.0 / 200.0 * f / (400.0 - f))


def _sharpness(rgb: np.ndarray) -> float:
    grey = rgb.astype(float).mean(axis=2)
    return float(np.var(np.diff(grey, axis=0)) + np.var(np.diff(grey, axis=1)))


@pytest.fixture(scope="module")
def scene() -> SubjectScene:
    box = trimesh.creation.box(extents=[300.0, 300.0, 300.0])  # near face at x = 150 mm
    box.apply_translation([0.0, 0.0, 1000.0])
    return SubjectScene(box)


def test_render_is_sharpest_with_the_lens_on_the_subject(scene: SubjectScene) -> None:
    renderer = PhoneRenderer(scene, DEFAULT_OPTICS, 96, 128)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = [0, 1, 0], [0, 0, -1], [-1, 0, 0]  # looks along -x
    pose[:3, 3] = [550.0, 0.0, 1000.0]  # 400 mm from the box's near face
    sharp = renderer.render(pose, 400.0)
    assert sharp.shape == (128, 96, 3) and sharp.dtype == np.uint8
    assert sharp[64, 48].mean() > 100 and sharp[2, 2].mean() < 40  # skin in the middle, background at the corner
    assert _sharpness(sharp) > _sharpness(renderer.render(pose, 150.0))
    assert _sharpness(sharp) > _sharpness(renderer.render(pose, 2000.0))


def test_jpeg_and_test_card() -> None:
    card = empty_rig_picture(64, 48, seed=1)
    assert card.shape == (48, 64, 3)
    assert np.array_equal(card, empty_rig_picture(64, 48, seed=1))
    assert Image.open(io.BytesIO(encode_jpeg(card))).size == (64, 48)


def test_sensor_clock_inverse() -> None:
    phone = SimulatedPhone("CLOCK001", seed=5)
    for t in (0.0, 12.5, 3600.0):
        assert phone.loop_time_of(phone.sensor_ns(t)) == pytest.approx(t, abs=1e-8)
    other = SimulatedPhone("CLOCK002", seed=6)
    assert other.clock_offset_s != phone.clock_offset_s and other.clock_drift_ppm != phone.clock_drift_ppm


@pytest.mark.realtime
def test_standalone_server_serves_until_sigterm() -> None:
    code = ("import asyncio, argparse, sys; from sim.processes.phone import add_arguments, serve; "
            "p = argparse.ArgumentParser(); add_arguments(p); "
            "sys.exit(asyncio.run(serve(p.parse_args(sys.argv[1:]))))")
    proc = subprocess.Popen([sys.executable, "-c", code, "--port", "0", "--serial", "STANDALONE1",
                             "--file", "/sdcard/x.bin=1000"], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "STANDALONE1" in line and "127.0.0.1:" in line
        port = int(line.rsplit(":", 1)[1])
        script = ("import asyncio; from drivers.adb.auth import AdbKey; from drivers.adb.connection import "
                  "AdbConnection; from drivers.adb.transport import open_tcp\n"
                  "async def main():\n"
                  f"    c = AdbConnection(await open_tcp('127.0.0.1', {port}), AdbKey.generate())\n"
                  "    await c.connect(); s = await c.sync()\n"
                  "    print(len(await s.pull_bytes('/sdcard/x.bin'))); await s.close(); await c.close()\n"
                  "asyncio.run(main())")
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
        assert out.stdout.strip().endswith("1000"), out.stderr
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_defocus_blurs_each_level_as_if_over_the_whole_picture() -> None:
    """Blurring only the box round a level's pixels gives the pixels the whole picture would."""
    from scipy.ndimage import gaussian_filter

    from drivers.sim.phone_render import BLUR_LEVELS_PX

    rng = np.random.default_rng(4)
    rgb = rng.uniform(0, 255, (90, 70, 3)).astype(np.float32)
    coc = np.zeros((90, 70))
    coc[10:30, 5:25] = 2.0  # a patch inside the picture
    coc[60:, 50:] = 8.0  # a patch at the picture's corner
    coc[40:45, :] = 16.0  # a band across it
    levels = np.array(BLUR_LEVELS_PX)
    index = np.searchsorted((levels[1:] + levels[:-1]) / 2, coc)
    expected = rgb.copy()
    for i in np.unique(index):
        if levels[i]:
            whole = gaussian_filter(rgb, sigma=(levels[i] / 2, levels[i] / 2, 0), truncate=3.0)
            expected[index == i] = whole[index == i]
    assert np.array_equal(PhoneRenderer._defocus(rgb, coc), np.clip(expected, 0, 255).astype(np.uint8))


def test_render_scale_gives_the_simulated_rig_s_phones_finer_pictures_of_the_same_view() -> None:
    from sim.clock import run_virtual
    from sim.rig import SimOptions, build_sim_rig
    from tests.daemon_rigs import capsule_subject

    rig = load_rig()
    subject = capsule_subject()

    async def pictures(scale: int) -> list[tuple[tuple[int, int], np.ndarray]]:
        _hardware, world = await build_sim_rig(rig, SimOptions(depth_decimation=8, render_scale=scale), subject=subject)
        try:
            shot = []
            for phone in world.phones[2:4]:
                info = phone.camera_info()
                jpeg = phone._picture(phone.pose(0.0), 1000.0 / 280.0, 0)  # the capsule's skin ~280 mm off
                shot.append(((info["image_width"], info["image_height"]),
                             np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"), dtype=float)))
            return shot
        finally:
            await world.close()

    coarse, fine = run_virtual(pictures(1)), run_virtual(pictures(2))
    for (coarse_size, coarse_rgb), (fine_size, fine_rgb) in zip(coarse, fine):
        assert coarse_size == (192, 256) and coarse_rgb.shape == (256, 192, 3)
        assert fine_size == (384, 512) and fine_rgb.shape == (512, 384, 3)
        # the same view: the fine picture averaged over 2 x 2 pixels is the coarse one, up to
        # where the coarse pixel's single ray meets a freckle's edge
        binned = fine_rgb.reshape(256, 2, 192, 2, 3).mean(axis=(1, 3))
        assert np.corrcoef(binned.ravel(), coarse_rgb.ravel())[0, 1] > 0.99
        assert np.median(np.abs(binned - coarse_rgb)) < 4.0


@pytest.mark.parametrize("scale", [0, 33, 2.0, True])
def test_a_render_scale_that_is_not_a_whole_number_in_range_is_refused_naming_it(scale: object) -> None:
    from sim.rig import SimOptions

    with pytest.raises(ValueError, match=f"render_scale {scale!r}"):
        SimOptions(render_scale=scale)  # type: ignore[arg-type]


def test_a_simulated_scan_hands_its_render_scale_to_the_simulated_rig(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    import sim.run

    class Built(Exception):
        """The simulated rig was built (with the options it carries)."""

    async def build(_rig: object, options: object, **_kwargs: object) -> None:
        raise Built(options)

    monkeypatch.setattr(sim.run, "build_sim_rig", build)
    with pytest.raises(Built) as built:
        sim.run.run_sim_scan(store=tmp_path, render_scale=3)
    assert built.value.args[0].render_scale == 3
