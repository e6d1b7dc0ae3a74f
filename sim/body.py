"""Simulated subjects: realistic adult bodies from the Anny model, the world every simulator sees.

A body is a closed triangle mesh of the outer skin in the rig frame: millimetres, feet on z = 0,
the body's volume centroid on the rotation axis (x = y = 0), the subject's front looking toward
+x (beam angle 0 looks at the front) and its left toward +y; standing anatomical pose with the
arms lowered ARM_ABDUCTION_DEG from the vertical and the feet slightly apart. Bodies are cached
in the process and on disk (``$TBP_CACHE_DIR`` or ``~/.cache/tbp``), keyed by every parameter
and by this code's source, because many tests and benchmarks ask for the same few bodies.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import tempfile
from dataclasses import astuple, dataclass, fields
from pathlib import Path

import numpy as np
import structlog
import trimesh

from sim import anny
from sim.anny import ANKLE_SPACING_M, ARM_ABDUCTION_DEG
from sim.body_errors import BodyError, BodyFileError, PhenotypeError

__all__ = [
    "ADULT_AGE",
    "ANKLE_SPACING_M",
    "ARM_ABDUCTION_DEG",
    "Body",
    "MAX_SWAY_DEG",
    "Phenotype",
    "generate_body",
    "load_body",
    "load_subject",
    "make_body",
    "adult_of_stature",
    "random_adult_phenotype",
    "save_body",
    "seed_phenotype",
]

log = structlog.get_logger(__name__)

ADULT_AGE = (0.67, 0.92)
"""Anny's age control for adults: 2/3 is its 'young adult' (about 25 years) anchor, 1 is 'old'."""
AVERAGE_ADULT_AGE = 0.75
AVERAGE_ADULT_HEIGHT = 0.38
"""Anny's height control for a stature of about 1.70 m at gender 0.5 (0.5 gives about 1.84 m)."""
ADULT_STATURE_M = ((1.76, 0.07), (1.63, 0.065))
"""Mean and standard deviation of adult stature (m) for gender 0 (male) and 1 (female)."""
STATURE_LIMITS_M = (1.55, 1.95)
# Unposed stature (m) ~ 1 * c0 + gender, age, muscle, weight, height, proportions controls;
# least-squares fit over 40 random adults, largest error 23 mm.
_STATURE_MODEL = np.array([1.39180, -0.136538, -0.0556173, 0.0192854, 0.0100350, 1.08268, -0.00757853])
MAX_SWAY_DEG = 10.0
"""Postural sway is small; larger turns would make a different pose, not sway."""

# Rig frame from Anny's model frame: front (-y) becomes +x, left (+x) becomes +y, metres -> mm.
_MODEL_TO_RIG = 1000.0 * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Phenotype:
    """Anny's phenotype controls, each in its native range [0, 1].

    gender: 0 male .. 1 female; age: 2/3 young adult .. 1 old (below 2/3: children);
    muscle, weight, height: min .. max (height spans about 1.08 m of stature per unit, so
    adults of 1.5..2.0 m need height in about 0.1..0.75); proportions: ideal .. uncommon.
    Default: an average adult of about 1.70 m.
    """

    gender: float = 0.5
    age: float = AVERAGE_ADULT_AGE
    muscle: float = 0.5
    weight: float = 0.5
    height: float = AVERAGE_ADULT_HEIGHT
    proportions: float = 0.5

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise PhenotypeError(f.name, value, "not a number")
            if not math.isfinite(value):
                raise PhenotypeError(f.name, value, "not finite")
            if not 0.0 <= value <= 1.0:
                raise PhenotypeError(f.name, value, "outside [0, 1]")
            object.__setattr__(self, f.name, float(value))

    @classmethod
    def parse(cls, text: str) -> Phenotype:
        """Phenotype from "gender,age,muscle,weight,height,proportions", e.g. "0.5,0.75,0.5,0.5,0.5,0.5"."""
        names = [f.name for f in fields(cls)]
        parts = [p.strip() for p in text.split(",")] if text.strip() else []
        if len(parts) < len(names):
            raise PhenotypeError(names[len(parts)], None, f"missing: {text!r} has {len(parts)} of the "
                                 f"{len(names)} values {','.join(names)}")
        if len(parts) > len(names):
            raise PhenotypeError(names[-1], parts[len(names)], f"a value after {names[-1]} in {text!r}: "
                                 f"expected only {','.join(names)}")
        values = {}
        for name, part in zip(names, parts):
            try:
                values[name] = float(part)
            except ValueError:
                raise PhenotypeError(name, part, "not a number") from None
        return cls(**values)

    def shape(self) -> np.ndarray:
        """(6,) float32 Anny shape vector: gender, age, muscle, weight, height, proportions."""
        return np.array(astuple(self), dtype=np.float32)

    def __str__(self) -> str:
        return ",".join(f"{v:.4g}" for v in astuple(self))


def random_adult_phenotype(rng: np.random.Generator) -> Phenotype:
    """A varied adult: any gender, ages 25..~75, spread muscle and weight, realistic stature.

    The height control is solved from a stature drawn for the gender (ADULT_STATURE_M, clipped
    to STATURE_LIMITS_M) so that every body stands 1.5..2.0 m tall.
    """
    gender = float(rng.uniform(0.0, 1.0))
    others = dict(
        age=float(rng.uniform(*ADULT_AGE)),
        muscle=float(rng.uniform(0.2, 0.8)),
        weight=float(rng.uniform(0.15, 0.85)),
        proportions=float(rng.uniform(0.2, 0.8)),
    )
    (mean_m, sd_m), (mean_f, sd_f) = ADULT_STATURE_M
    stature = rng.normal(mean_m + gender * (mean_f - mean_m), sd_m + gender * (sd_f - sd_m))
    stature = float(np.clip(stature, *STATURE_LIMITS_M))
    c0, c_gender, c_age, c_muscle, c_weight, c_height, c_proportions = _STATURE_MODEL
    rest = (c0 + c_gender * gender + c_age * others["age"] + c_muscle * others["muscle"]
            + c_weight * others["weight"] + c_proportions * others["proportions"])
    height = float(np.clip((stature - rest) / c_height, 0.0, 1.0))
    return Phenotype(gender=gender, height=height, **others)


def adult_of_stature(stature_m: float, gender: float, **others: float) -> Phenotype:
    """An adult of the given standing height (m): the height control solved from the stature
    model, then corrected twice against the built body's measured height (the model errs by up
    to ~25 mm). ``others``: age, muscle, weight, proportions (default the average adult's)."""
    controls = dict(age=AVERAGE_ADULT_AGE, muscle=0.5, weight=0.5, proportions=0.5) | others
    c0, c_gender, c_age, c_muscle, c_weight, c_height, c_proportions = _STATURE_MODEL
    rest = (c0 + c_gender * gender + c_age * controls["age"] + c_muscle * controls["muscle"]
            + c_weight * controls["weight"] + c_proportions * controls["proportions"])
    height = (stature_m - rest) / c_height
    for _ in range(2):
        phenotype = Phenotype(gender=gender, height=float(np.clip(height, 0.0, 1.0)), **controls)
        measured_m = generate_body(phenotype=phenotype).height_mm / 1000.0
        height += (stature_m - measured_m) / c_height
    return Phenotype(gender=gender, height=float(np.clip(height, 0.0, 1.0)), **controls)


@dataclass(frozen=True)
class Body:
    """A generated subject: the skin mesh (rig frame, mm) and its joints (name -> (3,) mm)."""

    mesh: trimesh.Trimesh
    joints: dict[str, np.ndarray]
    phenotype: Phenotype
    sway_deg: float

    @property
    def height_mm(self) -> float:
        return float(self.mesh.bounds[1, 2] - self.mesh.bounds[0, 2])


def make_body(
    *, seed: int = 0, phenotype: Phenotype | None = None, sway_deg: float = 0.0, sway_seed: int | None = None
) -> trimesh.Trimesh:
    """The subject's outer skin: closed mesh in mm, feet on z = 0, centred, facing +x.

    Without a phenotype the seed draws a random adult (seed_phenotype(seed)). sway_deg turns
    each sway joint by that angle about an axis drawn from sway_seed (default: the seed), so
    make_body(seed=s, sway_deg=2, sway_seed=k) for k = 0, 1... sways one adult into many poses.
    Deterministic for given arguments; returns a fresh copy each call.
    """
    return generate_body(seed=seed, phenotype=phenotype, sway_deg=sway_deg, sway_seed=sway_seed).mesh.copy()


def seed_phenotype(seed: int) -> Phenotype:
    """The random adult that make_body(seed=seed) builds when given no phenotype."""
    return random_adult_phenotype(np.random.default_rng(_seeds(seed)[0]))


def generate_body(
    *, seed: int = 0, phenotype: Phenotype | None = None, sway_deg: float = 0.0, sway_seed: int | None = None
) -> Body:
    """make_body with the joints; cached in the process and on disk (treat the result as read-only)."""
    if not math.isfinite(sway_deg) or not 0.0 <= sway_deg <= MAX_SWAY_DEG:
        raise BodyError(f"sway_deg={sway_deg!r}: must be in [0, {MAX_SWAY_DEG}] degrees")
    if phenotype is None:
        phenotype = seed_phenotype(seed)
    sway_seed = seed if sway_seed is None else sway_seed
    # Without sway the seed has no further effect: one cache entry per phenotype.
    return _cached_body(phenotype, float(sway_deg), int(sway_seed) if sway_deg else 0)


@functools.lru_cache(maxsize=16)
def _cached_body(phenotype: Phenotype, sway_deg: float, sway_seed: int) -> Body:
    path = _cache_dir() / f"body-{_cache_key(phenotype, sway_deg, sway_seed)}.npz"
    body = _read_cached(path, phenotype, sway_deg)
    if body is None:
        sway_rng = np.random.default_rng(_seeds(sway_seed)[1])
        posed = anny.posed_body(phenotype.shape(), sway_deg=sway_deg, rng=sway_rng)
        body = _to_rig_frame(posed, phenotype, sway_deg)
        _write_cached(path, body)
    body.mesh.vertices.flags.writeable = False
    # Skin coordinates for the simulated cameras' freckles: the unswayed body of the same
    # phenotype (same vertices), so every visit of one person shows the same spots on the same skin.
    still = body if not sway_deg else _cached_body(phenotype, 0.0, 0)
    body.mesh.vertex_attributes["skin_mm"] = still.mesh.vertices
    return body


def _seeds(seed: int) -> list[np.random.SeedSequence]:
    """Independent streams of one seed: [0] draws the phenotype, [1] the sway axes."""
    return np.random.SeedSequence(int(seed)).spawn(2)


def _to_rig_frame(posed: anny.PosedBody, phenotype: Phenotype, sway_deg: float) -> Body:
    """Rotate to face +x, scale to mm, stand on z = 0 and centre the volume on the axis."""
    mesh = trimesh.Trimesh(posed.vertices @ _MODEL_TO_RIG.T, posed.faces.astype(np.int32), process=False)
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    if not mesh.is_watertight or not mesh.is_winding_consistent:
        raise BodyError(f"Anny skin for phenotype {phenotype} is not a closed consistently wound surface")
    offset = np.array([-mesh.center_mass[0], -mesh.center_mass[1], -mesh.bounds[0, 2]])
    # float32 positions (0.1 um at 2 m) so a body read from the disk cache equals a fresh one.
    mesh.vertices = (mesh.vertices + offset).astype(np.float32).astype(np.float64)
    joints = {name: p @ _MODEL_TO_RIG.T + offset for name, p in posed.joints.items()}
    return Body(mesh=mesh, joints=joints, phenotype=phenotype, sway_deg=sway_deg)


def _cache_dir() -> Path:
    root = os.environ.get("TBP_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "tbp"
    )
    return Path(root) / "bodies"


@functools.lru_cache(maxsize=1)
def _code_version() -> str:
    """Digest of the code that shapes a body, so an edited pose never reads a stale cache."""
    digest = hashlib.sha256()
    for module in (anny.__file__, __file__):
        digest.update(Path(module).read_bytes())
    from importlib.metadata import PackageNotFoundError, version

    for distribution in ("body-models", "anny"):
        try:
            digest.update(version(distribution).encode())
        except PackageNotFoundError:  # a missing distribution fails later, when the model loads
            digest.update(distribution.encode())
    return digest.hexdigest()


def _cache_key(phenotype: Phenotype, sway_deg: float, sway_seed: int) -> str:
    text = f"{_code_version()}|{astuple(phenotype)!r}|{sway_deg!r}|{sway_seed}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _read_cached(path: Path, phenotype: Phenotype, sway_deg: float) -> Body | None:
    """The cached body, or None when absent or unreadable (it is then rebuilt)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            mesh = trimesh.Trimesh(data["vertices"].astype(np.float64), data["faces"], process=False)
            joints = dict(zip(data["joint_names"].tolist(), data["joint_positions"]))
    except (OSError, ValueError, KeyError) as exc:
        log.warning("body_cache_unreadable", path=str(path), error=str(exc))
        return None
    return Body(mesh=mesh, joints=joints, phenotype=phenotype, sway_deg=sway_deg)


def _write_cached(path: Path, body: Body) -> None:
    """Write atomically (temporary file + rename) so concurrent processes never see half a file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".body-", suffix=".npz", delete=False) as tmp:
            try:
                np.savez(
                    tmp,
                    vertices=np.asarray(body.mesh.vertices, dtype=np.float32),
                    faces=np.asarray(body.mesh.faces, dtype=np.int32),
                    joint_names=np.array(list(body.joints)),
                    joint_positions=np.array(list(body.joints.values())),
                )
            except OSError:
                os.unlink(tmp.name)
                raise
        os.chmod(tmp.name, 0o644)  # like any other file, not the temporary file's 0600
        os.replace(tmp.name, path)
    except OSError as exc:
        log.warning("body_cache_not_written", path=str(path), error=str(exc))


SKIN_PROPERTIES = ("skin_x", "skin_y", "skin_z")
"""The PLY vertex properties (float, mm) holding a body's skin coordinates (``vertex_attributes
["skin_mm"]``: each vertex's place on the unswayed body, where the simulated freckles are fixed)."""


def save_body(mesh: trimesh.Trimesh, path: str | Path) -> None:
    """Write a body mesh (mm) as binary PLY (or any format trimesh knows from the suffix).

    Its skin coordinates, when it has them, are written as the vertex properties
    :data:`SKIN_PROPERTIES`, so a body read back (:func:`load_body`, :func:`load_subject`) shows the
    same skin; a format that cannot hold them is refused rather than losing the subject's skin."""
    path = Path(path)
    out = mesh.copy()
    skin = out.vertex_attributes.pop("skin_mm", None)
    if skin is not None:
        if path.suffix.lower() != ".ply":
            raise BodyFileError(path, f"a {path.suffix or 'suffix-less'} file cannot hold the body's skin "
                                      "coordinates; write .ply")
        for k, name in enumerate(SKIN_PROPERTIES):
            out.vertex_attributes[name] = np.asarray(skin, dtype=np.float32)[:, k]
    try:
        out.export(path)
    except (OSError, ValueError) as exc:
        raise BodyFileError(path, f"cannot write: {exc}") from exc


def with_skin(mesh: trimesh.Trimesh, path: Path) -> trimesh.Trimesh:
    """``mesh`` as read from ``path`` with the skin coordinates its PLY vertices carry, if any, as
    ``vertex_attributes["skin_mm"]``; BodyFileError when they no longer match the vertices (the
    reader merged or reordered them)."""
    raw = mesh.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    if raw is None or raw.dtype.names is None or not set(SKIN_PROPERTIES) <= set(raw.dtype.names):
        return mesh
    xyz = np.stack([raw[c] for c in "xyz"], axis=1).astype(float)
    if xyz.shape != mesh.vertices.shape or not np.array_equal(xyz, np.asarray(mesh.vertices)):
        raise BodyFileError(path, "its vertices changed when read (merged or reordered): its skin coordinates "
                                  "no longer match them")
    mesh.vertex_attributes["skin_mm"] = np.stack([raw[name] for name in SKIN_PROPERTIES], axis=1).astype(float)
    return mesh


def load_body(path: str | Path) -> trimesh.Trimesh:
    """Read a body mesh (mm) written by save_body or another tool; it must be one closed surface.
    Skin coordinates written by save_body come back as ``vertex_attributes["skin_mm"]``."""
    path = Path(path)
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh's parsers raise anything from IndexError to KeyError
        raise BodyFileError(path, f"cannot read: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise BodyFileError(path, "holds no triangles")
    if not mesh.is_watertight:
        raise BodyFileError(path, "is not watertight")
    return with_skin(mesh, path)


def load_subject(path: str | Path) -> trimesh.Trimesh:
    """The simulated world's subject from a mesh file (``--subject``): the planner's mesh reader
    (size and type checked) and the skin coordinates ``tbp body`` wrote, so each visit of one
    person shows the same freckles on the same skin."""
    from planner.plan import load_subject_mesh

    return with_skin(load_subject_mesh(path), Path(path))
