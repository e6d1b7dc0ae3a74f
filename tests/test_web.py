"""The web server on a small simulated scan: viewer API, navigation identical to `tbp navigate`,
lesion marks, and hostile requests refused with a clear 4xx that changes nothing."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from aiohttp.test_utils import TestClient, TestServer

from analysis.marks import MARKS
from analysis.navigate import navigate
from analysis.skin_map import read_skin_shares
from daemon.faults import AbortCause, AbortSource
from daemon.records.manifest import ScanEnd
from daemon.records.store import ScanStore, read_folder
from web.access import Access, AccessError, parse_listen
from web.app import make_app


@pytest.fixture
def store(web_store: Path) -> Path:
    """The shared simulated scan (read only: tests that write use scan_store's copy)."""
    return web_store


@pytest.fixture
def scan_store(store: Path, tmp_path: Path) -> Path:
    """A private copy (tests write marks)."""
    copy = tmp_path / "store"
    shutil.copytree(store, copy)
    return copy


async def client_for(root: Path, access: Access | None = None, service: object | None = None) -> TestClient:
    access = access or Access("127.0.0.1", 0)
    client = TestClient(TestServer(make_app(root, access, service=service), host="127.0.0.1"))
    await client.start_server()
    return client


def folder_of(root: Path) -> str:
    return next(p.name for p in root.iterdir() if p.is_dir())


async def test_navigation_over_the_web_is_tbp_navigate(scan_store):
    name = folder_of(scan_store)
    client = await client_for(scan_store)
    try:
        for vertex in (100, 50_000):
            web = await (await client.get(f"/api/scans/{name}/navigate", params={"vertex": vertex, "count": 5})).json()
            assert web == json.loads(json.dumps(navigate(scan_store / name, vertex=vertex, count=5)))
        point = web["point_mm"]
        q = {"x": point[0] + 3.0, "y": point[1], "z": point[2]}
        web = await (await client.get(f"/api/scans/{name}/navigate", params=q)).json()
        cli = navigate(scan_store / name, point=f"{q['x']},{q['y']},{q['z']}", count=len(web["views"]))
        assert web["views"] == json.loads(json.dumps(cli["views"])) and web["views"]
        best = web["views"][0]
        full = await client.get(f"/api/scans/{name}/images/{Path(best['file']).name}")
        assert full.status == 200 and await full.read() == (scan_store / name / best["file"]).read_bytes()
        crop = await client.get(f"/api/scans/{name}/images/{Path(best['file']).name}",
                                params={"u": best["u_px"], "v": best["v_px"]})
        assert crop.status == 200 and crop.content_type == "image/jpeg"
    finally:
        await client.close()


async def test_scan_list_detail_and_mesh(scan_store):
    name = folder_of(scan_store)
    client = await client_for(scan_store)
    try:
        scans = (await (await client.get("/api/scans")).json())["scans"]
        assert [s["folder"] for s in scans] == [name] and scans[0]["state"] == "complete"
        detail = await (await client.get(f"/api/scans/{name}")).json()
        assert len(detail["images"]) == 336 and detail["cameras"][0] == "cam0"
        body = await (await client.get(f"/api/scans/{name}/mesh")).read()
        import numpy as np
        import trimesh

        mesh = trimesh.load(scan_store / name / "mesh.ply", process=False)
        nv, nf = np.frombuffer(body[4:12], "<u4")
        assert body[:4] == b"TBPM" and (nv, nf) == (len(mesh.vertices), len(mesh.faces))
        positions = np.frombuffer(body, "<f4", 3 * nv, 44).reshape(-1, 3)
        assert np.array_equal(positions, np.asarray(mesh.vertices, dtype=np.float32))
        skin = np.frombuffer(body[44 + 12 * nv + 12 * nf:], np.uint8)
        assert len(skin) == nv and set(np.unique(skin)) <= {0, 1, 2} and (skin == 2).mean() > 0.5
        for page in ("/", "/scans", f"/scans/{name}", f"/scans/{name}/report/", "/vendor/three/build/three.module.js"):
            assert (await client.get(page)).status == 200, page
    finally:
        await client.close()


def _variant(root: Path, name: str, tag: str, end: Any) -> str:
    """A copy of the scan ``name`` ended otherwise by ``end(folder)``; its folder name."""
    copy = f"{name[:15]}-{tag}"
    shutil.copytree(root / name, root / copy)
    end(read_folder(root / copy))
    return copy


def _partial(folder: Any) -> None:
    for angle in range(5, 15):
        folder.update_image(2, angle, save=False, status="missing", missing_reason="phone_dropped")
    folder.update_image(4, 7, save=False, status="failed", missing_reason="pull_failed")
    folder.finish(ScanEnd.COMPLETE)


def _running(folder: Any) -> None:
    folder.manifest.state, folder.manifest.in_progress = ScanEnd.INCOMPLETE, True
    folder.save()


async def test_every_scan_that_is_not_complete_is_flagged_in_the_list_and_the_viewer(scan_store):
    """Partial, aborted, still running and recovered scans each say how they ended and why, with
    their missing images per phone; a complete scan says nothing more."""
    name = folder_of(scan_store)
    stop = AbortCause(AbortSource.STOP_BUTTON, "panel", "stop button")
    partial = _variant(scan_store, name, "partial", _partial)
    aborted = _variant(scan_store, name, "aborted", lambda f: f.finish(ScanEnd.ABORTED, [stop]))
    running = _variant(scan_store, name, "running", _running)
    recovered = _variant(scan_store, name, "recovered", _running)
    ScanStore(scan_store).recover("killed by test")
    _running(read_folder(scan_store / running))  # still running: recovery runs only at the daemon's start
    client = await client_for(scan_store)
    try:
        rows = {r["folder"]: r for r in (await (await client.get("/api/scans")).json())["scans"]}
        details = {f: await (await client.get(f"/api/scans/{f}")).json() for f in rows}
    finally:
        await client.close()
    for ended in (rows, details):
        complete = ended[name]
        assert (complete["state"], complete["in_progress"], complete["missing"], complete["reason"]) == (
            "complete", False, None, None)
        text = "11 of 336 images missing: cam2 10 (10 phone dropped); cam4 1 (1 pull failed)"
        assert ended[partial]["state"] == "partial" and ended[partial]["missing"] == ended[partial]["reason"] == text
        assert ended[partial]["missing_by_phone"] == {"cam2": {"phone_dropped": 10}, "cam4": {"pull_failed": 1}}
        assert ended[aborted]["state"] == "aborted" and ended[aborted]["reason"] == "panel: stop button"
        assert ended[running]["in_progress"] is True and ended[running]["missing"] is None
        assert ended[recovered]["state"] == "incomplete" and ended[recovered]["reason"] == "killed by test"
    images = {(i["camera_index"], i["angle_index"]): i for i in details[partial]["images"]}
    assert images[2, 5]["missing_reason"] == "phone_dropped" and images[0, 0]["missing_reason"] is None


async def test_the_sharp_skin_is_the_report_s_in_the_viewer_and_the_list(scan_store):
    name = folder_of(scan_store)
    client = await client_for(scan_store)
    try:
        viewer = await (await client.get(f"/api/scans/{name}/skin")).json()
        listed = (await (await client.get("/api/scans")).json())["scans"][0]["sharp_skin"]
    finally:
        await client.close()
    assert viewer == read_skin_shares(scan_store / name) and listed == viewer["sharp"]
    assert f"Sharp skin: <b>{100 * listed:.1f} %</b>" in (scan_store / name / "report" / "index.html").read_text()


async def test_marks_are_saved_beside_the_scan_and_never_touch_its_record(scan_store):
    name = folder_of(scan_store)
    folder = scan_store / name
    before = {p: p.read_bytes() for p in [folder / "manifest.json", *sorted((folder / "images").iterdir())]}
    client = await client_for(scan_store)
    try:
        on_skin = (await (await client.get(f"/api/scans/{name}/navigate", params={"vertex": 4242})).json())["point_mm"]
        reply = await client.post(f"/api/scans/{name}/marks", json={"name": "naevus, left flank", "point_mm": on_skin})
        assert reply.status == 201
        mark = await reply.json()
        listed = await (await client.get(f"/api/scans/{name}/marks")).json()
        assert [(m["name"], m["number"]) for m in listed["marks"]] == [("naevus, left flank", 1)]
        assert json.loads((folder / MARKS).read_text())["marks"][0]["id"] == mark["id"]
        assert (await client.delete(f"/api/scans/{name}/marks/{mark['id']}", json={})).status == 200
        assert (await (await client.get(f"/api/scans/{name}/marks")).json())["marks"] == []
    finally:
        await client.close()
    assert {p: p.read_bytes() for p in before} == before


async def test_an_image_damaged_in_the_store_gets_a_json_error_naming_it(scan_store):
    name = folder_of(scan_store)
    picture = scan_store / name / "images" / "cam0-a00.jpg"
    picture.write_bytes(picture.read_bytes()[:300])
    client = await client_for(scan_store)
    try:
        for query in ("size=thumb", "size=preview", "u=100&v=100"):
            reply = await client.get(f"/api/scans/{name}/images/cam0-a00.jpg?{query}")
            assert reply.status == 500 and reply.content_type == "application/json", query
            error = (await reply.json())["error"]
            assert error["type"] == "ImageUnreadable" and "cam0-a00.jpg does not decode" in error["message"]
        # the other images are served as before
        assert (await client.get(f"/api/scans/{name}/images/cam1-a00.jpg?size=thumb")).status == 200
    finally:
        await client.close()


@pytest.mark.parametrize("damage", ["cut short", "deleted"])
async def test_a_damaged_mesh_gets_a_json_409_naming_it_wherever_the_viewer_needs_the_mesh(scan_store, damage):
    name = folder_of(scan_store)
    mesh = scan_store / name / "mesh.ply"
    if damage == "deleted":
        mesh.unlink()
    else:
        mesh.write_bytes(mesh.read_bytes()[: mesh.stat().st_size // 2])
    client = await client_for(scan_store)
    try:
        for method, path, kwargs in (("GET", "navigate?vertex=100", {}), ("GET", "marks", {}),
                                     ("POST", "marks", {"json": {"name": "naevus", "point_mm": [0, 0, 1000]}})):
            reply = await client.request(method, f"/api/scans/{name}/{path}", **kwargs)
            assert reply.status == 409 and reply.content_type == "application/json", (method, path, await reply.text())
            error = (await reply.json())["error"]
            assert error["type"] == "ScanFileError" and "mesh.ply" in error["message"], (method, path)
    finally:
        await client.close()


@pytest.mark.parametrize("method, path, kwargs, status", [
    ("GET", "/api/scans/..%2F..%2Fetc/navigate?vertex=1", {}, 404),
    ("GET", "/api/scans/{name}/images/..%2Fmanifest.json", {}, 404),
    ("GET", "/api/scans/{name}/images/%2Fetc%2Fpasswd", {}, 404),
    ("GET", "/static/../../../../etc/passwd", {}, 404),
    ("GET", "/vendor/three/..%2F..%2Fapp.py", {}, 404),
    ("GET", "/scans/{name}/report/..%2Fmanifest.json", {}, 404),
    ("GET", "/api/scans/{name}/navigate?vertex=999999999", {}, 400),
    ("GET", "/api/scans/{name}/navigate?x=nan&y=1&z=1", {}, 400),
    ("GET", "/api/scans/{name}/navigate?x=1", {}, 400),
    ("GET", "/api/scans/{name}/images/cam0-a00.jpg?u=1&v=1&half=-3", {}, 400),
    ("POST", "/api/scans/{name}/marks", {"data": b"{not json", "headers": {"Content-Type": "application/json"}}, 400),
    ("POST", "/api/scans/{name}/marks", {"data": b"[1, 2]", "headers": {"Content-Type": "application/json"}}, 400),
    ("POST", "/api/scans/{name}/marks", {"json": {"name": "x", "point_mm": [1, "a", 3]}}, 400),
    ("POST", "/api/scans/{name}/marks", {"json": {"name": "", "point_mm": [1, 2, 3]}}, 400),
    ("POST", "/api/scans/{name}/marks", {"json": {"name": "x" * 81, "point_mm": [1, 2, 3]}}, 400),
    ("POST", "/api/scans/{name}/marks", {"data": b"name=x", "headers": {"Content-Type": "text/plain"}}, 415),
    ("POST", "/api/scans/{name}/marks", {"data": b"{" + b" " * 200_000 + b"}",
                                         "headers": {"Content-Type": "application/json"}}, 413),
    ("POST", "/api/scans/{name}/marks", {"json": {"name": "x", "point_mm": [1, 2, 3]},
                                         "headers": {"Origin": "http://evil.example"}}, 403),
    ("GET", "/api/scans", {"headers": {"Host": "evil.example:80"}}, 421),
    ("DELETE", "/api/scans/{name}/marks/../../x", {"json": {}}, 405),
    ("PUT", "/api/scans/{name}/previous", {"json": {"previous_scan": "../other"}}, 404),
    ("POST", "/api/rig/scan", {"json": {}}, 503),
])
async def test_hostile_requests_get_a_clear_4xx_and_change_nothing(scan_store, method, path, kwargs, status):
    name = folder_of(scan_store)
    snapshot = {p: p.read_bytes() for p in scan_store.rglob("*") if p.is_file()}
    client = await client_for(scan_store)
    try:
        reply = await client.request(method, path.format(name=name), **kwargs)
        assert reply.status == status, await reply.text()
        if path.startswith("/api/") and status != 421:
            assert reply.content_type == "application/json"
            assert (await reply.json())["error"]["message"]
    finally:
        await client.close()
    assert {p: p.read_bytes() for p in scan_store.rglob("*") if p.is_file()} == snapshot


class RecordingService:
    """The control handler's interface, recording calls (the real one is tested in the console test)."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def status(self):
        return {"state": "IDLE"}

    async def scan(self, **args):
        self.calls.append("scan")
        return {"scan_id": "x", "state": "PREPARING"}

    def abort(self):
        self.calls.append("abort")
        return {"aborted": False}

    async def reset(self):
        self.calls.append("reset")
        return {"state": "IDLE"}


async def test_control_needs_the_token_beyond_loopback(scan_store):
    service = RecordingService()
    token = "s3cret-operator-token"
    open_wide = await client_for(scan_store, Access("0.0.0.0", 0, open_reads=True), service)
    with_token = await client_for(scan_store, Access("0.0.0.0", 0, token), service)
    local = await client_for(scan_store, Access("127.0.0.1", 0), service)
    try:
        assert (await open_wide.post("/api/rig/scan", json={})).status == 403
        assert (await with_token.post("/api/rig/scan", json={})).status == 401
        bad = await with_token.post("/api/rig/abort", json={}, headers={"Authorization": "Bearer wrong-token-123456"})
        assert bad.status == 401 and service.calls == []
        good = await with_token.post("/api/rig/abort", json={}, headers={"Authorization": f"Bearer {token}"})
        assert good.status == 200 and service.calls == ["abort"]
        assert (await local.post("/api/rig/reset", json={})).status == 200 and service.calls[-1] == "reset"
        assert (await local.get("/api/rig/status")).status == 200
    finally:
        for c in (open_wide, with_token, local):
            await c.close()


async def test_beyond_loopback_every_reader_logs_in_first(scan_store):
    service = RecordingService()
    token = "s3cret-operator-token"
    name = folder_of(scan_store)
    client = await client_for(scan_store, Access("0.0.0.0", 0, token), service)
    try:
        for path in ("/api/scans", f"/api/scans/{name}", f"/api/scans/{name}/mesh", "/api/rig/status"):
            refused = await client.get(path)
            assert refused.status == 401, path
            assert "log in" in (await refused.json())["error"]["message"]
        page = await client.get(f"/scans/{name}", allow_redirects=False)
        assert page.status == 303 and page.headers["Location"] == f"/login?next=/scans/{name}"
        assert (await client.get("/static/style.css")).status == 200  # assets hold no patient data
        wrong = await client.post("/login", data={"token": "not-the-token-at-all", "next": "/scans"},
                                  allow_redirects=False)
        assert wrong.status == 401 and "not the operator token" in await wrong.text()
        assert (await client.get("/api/scans")).status == 401
        hostile = await client.post("/login", data={"token": token, "next": "//evil.example/x"},
                                    allow_redirects=False)
        assert hostile.status == 303 and hostile.headers["Location"] == "/"
        cookie = hostile.cookies["tbp_session"]
        assert token not in cookie.value and cookie["httponly"] and cookie["samesite"] == "Strict"
        listing = await client.get("/api/scans")
        assert listing.status == 200 and (await listing.json())["scans"]
        assert (await client.get(f"/scans/{name}", allow_redirects=False)).status == 200
        assert (await client.post("/api/rig/abort", json={})).status == 200 and service.calls == ["abort"]
        await client.post("/logout", allow_redirects=False)
        assert (await client.get("/api/scans")).status == 401
        bearer = await client.get("/api/scans", headers={"Authorization": f"Bearer {token}"})
        assert bearer.status == 200
    finally:
        await client.close()


def test_serving_beyond_loopback_needs_a_login_or_an_explicit_open_viewer():
    with pytest.raises(AccessError, match="--http-token-file.*--http-open-reads"):
        Access("0.0.0.0", 8470)
    assert not Access("0.0.0.0", 8470, open_reads=True).login_required
    assert Access("0.0.0.0", 8470, "0123456789abcdef").login_required
    assert not Access("127.0.0.1", 8470).login_required


@pytest.mark.parametrize("target, expected", [
    ("/scans/x?y=1", "/scans/x?y=1"), ("//evil.example", "/"), ("https://evil.example/", "/"),
    ("", "/"), (None, "/"), ("scans", "/"), ("/\\evil", "/"),
])
def test_login_returns_only_to_a_path_on_this_server(target, expected):
    from web.access import safe_next

    assert safe_next(target) == expected


def test_listen_address_is_checked():
    assert parse_listen("127.0.0.1:8470") == ("127.0.0.1", 8470)
    assert parse_listen("[::1]:80") == ("::1", 80)
    for bad in ("8470", "host:", "host:99999", ":80"):
        with pytest.raises(AccessError, match="--http"):
            parse_listen(bad)


def test_mesh_colours_agree_with_navigation(store):
    """A vertex coloured sharp has an in-focus verified image; unseen has no image at all."""
    import numpy as np

    from analysis.navigate import Navigator
    from analysis.scan_views import open_scan
    from analysis.skin_map import BLURRED, SHARP, UNSEEN, read_skin_mesh, skin_mesh_status

    scan = open_scan(store / folder_of(store))
    payload = read_skin_mesh(scan)
    assert payload is not None  # written by the QA report at the end of the scan
    skin = {"status": skin_mesh_status(payload)}
    navigator = Navigator(scan)
    rng = np.random.default_rng(4)
    checked = set()
    for status in (SHARP, BLURRED, UNSEEN):
        candidates = np.flatnonzero(skin["status"] == status)
        for vertex in rng.choice(candidates, size=min(6, len(candidates)), replace=False):
            views = navigator.query(vertex=int(vertex), count=None)["views"]
            assert (status == SHARP) == any(v["in_focus"] for v in views), (status, vertex)
            assert (status == UNSEEN) == (not views), (status, vertex)
            checked.add(status)
    assert {SHARP, UNSEEN} <= checked


async def test_marks_of_the_earlier_scan_are_carried_to_the_later_one(scan_store):
    """The same scan stored again as a 'later visit': its earlier marks land where they were."""
    import numpy as np

    earlier = folder_of(scan_store)
    later = "20991231-000000-" + earlier.split("-", 2)[2]
    shutil.copytree(scan_store / earlier, scan_store / later)
    client = await client_for(scan_store)
    try:
        vertex = (await (await client.get(f"/api/scans/{earlier}/navigate", params={"vertex": 4242})).json())["point_mm"]
        assert (await client.post(f"/api/scans/{earlier}/marks", json={"name": "naevus", "point_mm": vertex})).status == 201
        assert (await client.put(f"/api/scans/{earlier}/previous", json={"previous_scan": later})).status == 400
        assert (await client.put(f"/api/scans/{later}/previous", json={"previous_scan": earlier})).status == 200
        listed = await (await client.get(f"/api/scans/{later}/marks")).json()
        assert listed["previous_scan"] == earlier and listed["marks"] == []
        (carried,) = listed["carried"]
        assert carried["name"] == "naevus" and listed["registration"]["fitness"] > 0.99
        assert np.linalg.norm(np.subtract(carried["point_mm"], vertex)) < 1.0
        # the same pictures: the skin around the mark matches itself
        assert carried["placed_by"] == "pictures" and carried["picture_score"] > 0.95, carried
        assert carried["surface_gap_mm"] < 1.0 and not carried["in_doubt"], carried
        # a second earlier mark: both listed, the first where it was
        other = (await (await client.get(f"/api/scans/{earlier}/navigate", params={"vertex": 777})).json())["point_mm"]
        assert (await client.post(f"/api/scans/{earlier}/marks", json={"name": "lentigo", "point_mm": other})).status == 201
        again = await (await client.get(f"/api/scans/{later}/marks")).json()
        assert [m["name"] for m in again["carried"]] == ["naevus", "lentigo"] and again["carried"][0] == carried
        assert np.linalg.norm(np.subtract(again["carried"][1]["point_mm"], other)) < 1.0
    finally:
        await client.close()


@pytest.mark.slow
def test_marks_carry_to_a_swayed_later_visit():
    """The same adult, swayed 2 deg per joint and standing 29 mm and 6 deg elsewhere: marks on
    the earlier body land on the same skin point of the later one (body meshes, no scan; the
    web benchmark measures it on two simulated scans)."""
    import numpy as np

    from analysis.registration import MarkCarrier
    from sim.body import make_body
    from tests.web_visits import SWAY_DEG, VISIT_SHIFT_MM, VISIT_TURN_DEG, placed

    earlier = make_body(seed=3)
    later = placed(make_body(seed=3, sway_deg=SWAY_DEG, sway_seed=307), VISIT_SHIFT_MM, VISIT_TURN_DEG)
    rng = np.random.default_rng(0)
    marks = rng.choice(np.flatnonzero(np.asarray(earlier.vertices)[:, 2] > 150.0), size=40, replace=False)
    carried = MarkCarrier(earlier, later).carry(np.asarray(earlier.vertices)[marks]).points_mm
    error = np.linalg.norm(carried - np.asarray(later.vertices)[marks], axis=1)
    assert np.median(error) < 2.0 and np.mean(error <= 5.0) >= 0.9, np.sort(error)


def test_a_mark_on_skin_the_later_scan_reconstructed_inside_is_in_doubt():
    """Where the later scan's surface is a centimetre inside the skin (an occluded gap), the
    carried mark says so; elsewhere the later surface is where the fit puts the skin."""
    import numpy as np

    from analysis.registration import MarkCarrier
    from sim.body import make_body
    from tests.web_visits import dented

    earlier = make_body(seed=3)
    vertices = np.asarray(earlier.vertices)
    marks = vertices[[int(np.argmax(vertices[:, 0])), int(np.argmin(vertices[:, 0])), int(np.argmax(vertices[:, 2]))]]
    carried = MarkCarrier(earlier, dented(earlier, marks[0], 40.0, 10.0)).carry(marks)
    assert carried.in_doubt.tolist() == [True, False, False], carried.surface_gap_mm
    assert carried.surface_gap_mm[0] > 5.0 and np.all(carried.surface_gap_mm[1:] < 1.0), carried.surface_gap_mm
    # a shallower dent, under SURFACE_DOUBT_MM: still in doubt, the skin around matching closer than that
    shallow = MarkCarrier(earlier, dented(earlier, marks[0], 40.0, 2.5)).carry(marks)
    assert 1.5 < shallow.surface_gap_mm[0] < MarkCarrier.SURFACE_DOUBT_MM, shallow.surface_gap_mm
    assert shallow.surface_gap_mm[0] > shallow.fit_rmse_mm[0], (shallow.surface_gap_mm, shallow.fit_rmse_mm)
    assert shallow.in_doubt.tolist() == [True, False, False], (shallow.surface_gap_mm, shallow.fit_rmse_mm)


def test_a_mark_where_the_two_scans_surfaces_part_around_it_is_in_doubt():
    """A broad 3 mm dent (120 mm across) the local fit follows: the later surface is where the
    fit puts the skin (under the fit's residual), but around the mark the two surfaces lie more
    than SURFACE_NOISE_MM apart, so no rigid fit places the mark to the millimetre."""
    import numpy as np

    from analysis.registration import MarkCarrier
    from sim.body import make_body
    from tests.web_visits import dented

    earlier = make_body(seed=3)
    vertices = np.asarray(earlier.vertices)
    marks = vertices[[int(np.argmax(vertices[:, 0])), int(np.argmin(vertices[:, 0])), int(np.argmax(vertices[:, 2]))]]
    same = MarkCarrier(earlier, earlier).carry(marks)
    assert not same.in_doubt.any() and np.all(same.surfaces_apart_mm < 0.1), same.surfaces_apart_mm
    carried = MarkCarrier(earlier, dented(earlier, marks[0], 120.0, 3.0)).carry(marks)
    assert carried.surface_departs.tolist() == [False, False, False], (carried.surface_gap_mm, carried.fit_rmse_mm)
    assert carried.surfaces_apart_mm[0] > 1.3 and np.all(carried.surfaces_apart_mm[1:] < 0.1), carried.surfaces_apart_mm
    assert carried.surfaces_part.tolist() == carried.in_doubt.tolist() == [True, False, False]


def test_token_file_is_checked(tmp_path):
    from web.access import read_token

    short = tmp_path / "short"
    short.write_text("abc\n")
    with pytest.raises(AccessError, match="needs 16 or more"):
        read_token(short)
    with pytest.raises(AccessError, match="--http-token-file"):
        read_token(tmp_path / "absent")
    good = tmp_path / "token"
    good.write_text("  0123456789abcdefXYZ \n")
    assert read_token(good) == "0123456789abcdefXYZ"


def test_daemon_refuses_a_bad_http_address(capsys):
    from cli import main

    assert main(["daemon", "--sim", "--http", "localhost"]) == 2
    assert "expected HOST:PORT" in capsys.readouterr().err


async def test_a_scan_is_read_off_the_loop_once_per_manifest_and_again_when_it_is_rewritten(scan_store, monkeypatch):
    """A scan in progress rewrites its manifest after every image while the console polls it:
    each manifest is read once, in a thread (the daemon's loop carries the rig's heartbeats)."""
    import asyncio
    import threading

    import web.scans
    from daemon.records.store import ScanStore

    reads: list[str] = []
    real = web.scans.open_scan

    def counted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        reads.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(web.scans, "open_scan", counted)
    name = folder_of(scan_store)
    client = await client_for(scan_store)
    try:
        answers = await asyncio.gather(*(client.get(f"/api/scans/{name}") for _ in range(4)))
        assert [a.status for a in answers] == [200] * 4
        assert (await client.get(f"/api/scans/{name}/images/none.jpg")).status == 404
        assert len(reads) == 1
        folder = ScanStore(scan_store).open(scan_store / name)
        folder.update_image(0, 0, error="re-checked")  # rewritten (atomically: another file)
        detail = await (await client.get(f"/api/scans/{name}")).json()
        assert detail["images"][0]["error"] == "re-checked" and len(reads) == 2
        assert threading.current_thread().name not in reads
    finally:
        await client.close()


class MachineService:
    """The rig handler's status, history and events, from a real state machine."""

    def __init__(self) -> None:
        from daemon.rig.states import ScanStateMachine

        self.machine = ScanStateMachine()

    def status(self):
        return {"state": self.machine.state.value}

    def recent_events(self):
        return [e.as_dict() for e in self.machine.recent]

    async def subscribe(self):
        async for event in self.machine.subscribe():
            yield event.as_dict()


async def _sse_until(response, kind: str) -> list[tuple[str, Any]]:
    """(event, data) pairs read from a Server-Sent Events stream up to the first ``kind``."""
    got: list[tuple[str, Any]] = []
    event = None
    while True:
        line = (await response.content.readline()).decode().rstrip("\n")
        if line.startswith("event: "):
            event = line[7:]
        elif line.startswith("data: "):
            got.append((event, json.loads(line[6:])))
            if event == kind:
                return got


async def test_the_event_stream_starts_with_the_history_then_only_new_events(scan_store):
    from daemon.rig.states import ScanState

    service = MachineService()
    service.machine.transition(ScanState.PREPARING, "scan requested")
    service.machine.progress("captured", captured=1)
    service.machine.progress("phone_dropped", camera="cam2")
    client = await client_for(scan_store, service=service)
    try:
        response = await client.get("/api/rig/events")
        first = await _sse_until(response, "status")
        assert [kind for kind, _ in first] == ["history", "status"]
        history = first[0][1]
        assert [e["cause"] for e in history] == ["scan requested", "phone_dropped"]
        assert all(e["utc"] and e["seq"] for e in history)
        service.machine.transition(ScanState.ABORTING, "abort")
        live = [data for kind, data in await _sse_until(response, "rig") if kind == "rig"]
        assert live[-1]["cause"] == "abort" and live[-1]["seq"] > history[-1]["seq"]
        response.close()
    finally:
        await client.close()


async def test_a_mark_off_the_body_or_on_an_existing_mark_is_refused_naming_why(scan_store):
    """Marks lie on the body (within 5 mm of the mesh) and one spot has one mark; each refusal says
    why (the distance; the existing mark's number and name) and stores nothing."""
    import numpy as np

    name = folder_of(scan_store)
    client = await client_for(scan_store)
    marks = f"/api/scans/{name}/marks"
    try:
        spot = (await (await client.get(f"/api/scans/{name}/navigate", params={"vertex": 4242})).json())
        point = np.array(spot["point_mm"])
        first = await client.post(marks, json={"name": "naevus", "point_mm": point.tolist()})
        assert first.status == 201 and (await first.json())["number"] == 1
        far = (point + np.array([5000.0, 0.0, 0.0])).tolist()
        off = await client.post(marks, json={"name": "nowhere", "point_mm": far})
        error = (await off.json())["error"]
        assert off.status == 400 and error["type"] == "MarkOffBody", error
        assert "mm from this scan's body surface" in error["message"] and "within 5 mm" in error["message"]
        again = await client.post(marks, json={"name": "naevus again", "point_mm": (point + [0.0, 0.0, 1.0]).tolist()})
        error = (await again.json())["error"]
        assert again.status == 409 and error["type"] == "MarkDuplicate"
        assert "mark 1 'naevus' is 1.0 mm from this point" in error["message"], error
        empty = await client.post(marks, json={"name": "  ", "point_mm": point.tolist()})
        assert empty.status == 400 and "give a name" in (await empty.json())["error"]["message"]
        other = (await (await client.get(f"/api/scans/{name}/navigate", params={"vertex": 777})).json())["point_mm"]
        second = await client.post(marks, json={"name": "lentigo", "point_mm": other})
        assert second.status == 201 and (await second.json())["number"] == 2
        listed = await (await client.get(marks)).json()
        assert [(m["number"], m["name"]) for m in listed["marks"]] == [(1, "naevus"), (2, "lentigo")]
        assert all(m["region"] for m in listed["marks"]) and listed["body"]["z_max_mm"] > 1000.0
    finally:
        await client.close()
