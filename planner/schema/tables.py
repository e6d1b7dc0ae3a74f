"""The table of every configuration file: the rig file, the calibration file, the calibration
target, the focus tables, the site file and (given the depth camera kinds) the hardware file.

Every key's form, range and default is here; the modules that turn the values into dataclasses
(planner/rig.py, planner/calibration/model.py and target.py, drivers/phone/focus.py,
daemon/rig/hardware_config.py) check only the relations between keys, listed in each file's rules.
docs/configuration.md is generated from these tables (tests/test_config_docs.py).
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from planner.schema.config_file import ConfigFile
from planner.schema.nodes import (
    Choice,
    Flag,
    Id,
    Integer,
    Kind,
    Kinds,
    ListOf,
    MapOf,
    Node,
    Note,
    Nullable,
    Number,
    Section,
    Serial,
    Text,
    Tuple,
)

# ---------------------------------------------------------------------------- rig file

_OPTICS = Section({
    "focal_length_mm": Number(1.0, 100.0),
    "f_number": Number(0.7, 32.0),
    "hyperfocal_mm": Number(100.0, 1e6),
    "image_width_px": Integer(64, 100_000),
    "image_height_px": Integer(64, 100_000),
    "hfov_deg": Number(5.0, 120.0, doc="across image_width_px"),
    "exposure_s": Number(1e-5, 1.0),
    "iso": Integer(25, 25_600),
}, doc="the phones' lens and sensor")
_PHONE = Section({
    "id": Id(),
    "serial": Text(doc="ADB serial (ro.serialno)"),
    "height_mm": Number(0.0, 2600.0),
    "tilt_deg": Number(-60.0, 60.0, doc="> 0 looks up"),
    "focus_calibration": Text(doc="the phone's focus table, relative to the rig file"),
})
_SECTOR = Section({
    "name": Id(),
    "start_deg": Number(-360.0, 720.0),
    "end_deg": Number(-360.0, 720.0),
    "speed_deg_s": Number(0.1, 90.0),
    "first_capture_deg": Number(-360.0, 720.0),
    "capture_step_deg": Number(0.1, 180.0),
    "captures": Integer(1, 720, doc="capture angles first_capture_deg + k * capture_step_deg, k < captures"),
})
_CAPTURE = Section({
    "sectors": ListOf(_SECTOR, 1, 64, doc="spans of beam angle driven at one speed, in rotation order"),
    "acceleration_deg_s2": Number(0.1, 1000.0, doc="ramps between speeds and at start and end"),
    "max_motion_blur_px": Number(0.1, 100.0),
    "lens_settle_s": Number(0.0, 5.0),
    "capture_cycle_s": Number(0.0, 60.0, doc="phone: trigger to ready for the next capture"),
    "angle_tolerance_deg": Number(0.001, 10.0),
}, doc="the capture rotation")
_COST = Section({
    "w_area": Number(0.0, 1.0),
    "w_axis": Number(0.0, 1.0),
    "w_focus": Number(0.0, 1.0),
    "area_reference_distance_mm": Number(1.0, 1e5),
    "area_reference_incidence_deg": Number(0.0, 89.9),
    "axis_deviation_mm": Number(1.0, 1e5),
}, doc="the focus cost (SPEC section 3)")
_PLANNER = Section({
    "points": Integer(100, 10_000_000, doc="planning samples on the body"),
    "em_relative_tolerance": Number(0.0, 0.5),
    "em_max_iterations": Integer(1, 10_000),
    "refine_max_sweeps": Integer(0, 10_000),
    "redundancy_weight": Number(0.0, 100.0, default=1.0, doc="robust focus: cost of one expected missed point"),
    "view_miss_probability": Number(0.01, 0.99, default=0.2,
                                    doc="the chance one sharp view of a sample fails on the real skin"),
    "robust_max_sweeps": Integer(0, 10_000, default=2),
    "per_subject_angles": Flag(default=False, doc="choose each scan's capture angles with its focus"),
    "angle_step_deg": Number(0.1, 30.0, default=1.0, doc="candidate capture angles this far apart"),
    "importance_density": Number(1.0, 16.0, default=1.0,
                                 doc="the skin few poses see, sampled this many times finer (1: off)"),
    "importance_views": Integer(1, 1_000, default=6, doc="'few poses': at most this many"),
    "importance_radius_mm": Number(1.0, 500.0, default=20.0, doc="and this far round it"),
})
_DEPTH_CAMERA = Section({
    "id": Id(),
    "serial": Text(),
    "radius_mm": Number(100.0, 5000.0),
    "angle_offset_deg": Number(-360.0, 360.0, doc="in the beam frame: 0 is the +x side at beam angle 0"),
    "height_mm": Number(0.0, 3000.0),
    "tilt_deg": Number(-89.0, 89.0),
    "roll_deg": Number(-180.0, 180.0),
})
_DEPTH_MODEL = Section({
    "width_px": Integer(16, 10_000),
    "height_px": Integer(16, 10_000),
    "fx_px": Number(1.0, 1e5),
    "fy_px": Number(1.0, 1e5),
    "cx_px": Number(0.0, 1e4),
    "cy_px": Number(0.0, 1e4),
    "fps": Number(0.1, 1000.0),
    "min_range_mm": Number(0.0, 1e4),
    "max_range_mm": Number(1.0, 1e5),
    "depth_unit_mm": Number(1e-3, 100.0),
    "baseline_mm": Number(1.0, 1000.0),
    "subpixel_px": Number(0.0, 10.0),
    "grazing_limit_deg": Number(1.0, 90.0),
})
_SWEEP = Section({
    "start_deg": Number(-360.0, 720.0),
    "end_deg": Number(-360.0, 720.0),
    "speed_deg_s": Number(0.1, 180.0),
}, doc="the depth sweep's rotation")
_TSDF = Section({
    "voxel_mm": Number(0.5, 50.0),
    "truncation_voxels": Number(1.0, 50.0),
    "weight_threshold": Number(0.0, 1000.0),
    "volume_radius_mm": Number(100.0, 5000.0),
    "volume_height_mm": Number(100.0, 5000.0),
    "floor_clearance_mm": Number(0.0, 200.0),
    "camera_clearance_mm": Number(0.0, 400.0, default=50.0,
                                  doc="skin closer than this to the phones' ring is refused before capture"),
    "surface_voxel_mm": Number(0.5, 50.0, default=4.0,
                               doc="the stored surface (mesh.ply): the sweep fused again at this voxel "
                                   "while the capture runs"),
})
_MOTOR = Section({
    "node_id": Integer(1, 127),
    "bitrate": Integer(10_000, 1_000_000),
    "gear_ratio": Number(0.01, 10_000.0, doc="motor turns per beam turn"),
    "encoder_counts_per_rev": Integer(1, 1 << 24, doc="per motor turn"),
    "max_speed_deg_s": Number(0.1, 360.0),
    "max_acceleration_deg_s2": Number(0.1, 10_000.0),
    "heartbeat_producer_ms": Integer(10, 10_000, doc="drive -> host"),
    "host_heartbeat_ms": Integer(10, 10_000, doc="host -> drive"),
    "heartbeat_timeout_ms": Integer(20, 60_000, doc="either side declares the other lost after this"),
    "following_error_deg": Number(0.01, 90.0),
    "position_rate_hz": Number(1.0, 10_000.0),
    "host_stall_ms": Integer(100, 5_000, default=500,
                             doc="the host's event loop stuck this long: the drive guard quick-stops the beam"),
}, doc="the beam drive (CANopen CiA 402)")
_RIG_CALIBRATION = Section({
    "file": Text(default="calibration.yaml", doc="the system calibration, relative to the rig file"),
    "max_age_days": Number(1.0, 3650.0, default=180.0, doc="older: scans warn"),
}, optional=True)

RIG_FILE = ConfigFile(
    what="rig file",
    where="calibration_data/rig.yaml; on a rig PC /etc/tbp-rig/rig.yaml",
    max_bytes=1024 * 1024,
    table=Section({
        "calibration": _RIG_CALIBRATION,
        "optics": _OPTICS,
        "ring": Section({"radius_mm": Number(100.0, 5000.0, doc="phone centre to the rotation axis")}),
        "phones": ListOf(_PHONE, 1, 64, doc="one vertical column of phones on the beam"),
        "capture": _CAPTURE,
        "cost": _COST,
        "planner": _PLANNER,
        "depth_cameras": ListOf(_DEPTH_CAMERA, 1, 16),
        "depth_camera_model": _DEPTH_MODEL,
        "depth_sweep": _SWEEP,
        "tsdf": _TSDF,
        "motor": _MOTOR,
    }, doc="what the rig is: geometry, optics, each device's identity"),
    rules=(
        "optics.hyperfocal_mm exceeds twice optics.focal_length_mm",
        "phone ids, phone serials, depth camera ids and sector names are each unique",
        ("each sector's end_deg exceeds its start_deg, its captures lie within them, and it starts "
         "where the previous one ends; the sectors span at most 360 deg"),
        "no sector's speed blurs a picture by more than capture.max_motion_blur_px at optics.exposure_s",
        "at least one of the cost weights is positive",
        "planner.points x the poses fit the planning memory budget (4 GiB)",
        "depth_camera_model.max_range_mm exceeds min_range_mm; depth_sweep.end_deg exceeds start_deg",
        "motor.heartbeat_timeout_ms exceeds motor.host_heartbeat_ms",
    ),
)

# ---------------------------------------------------------------------------- calibration file

CALIBRATION_FORMAT = "tbp-rig calibration 1"
_POSE = Section({
    "rotation_deg": Tuple.of(Number(-360.0, 360.0), 3, doc="rotation vector"),
    "translation_mm": Tuple.of(Number(-1e5, 1e5), 3),
})
_INTRINSICS = Section({
    "image_size_px": Tuple.of(Integer(1, 100_000), 2, doc="width, height"),
    "fx": Number(1.0, 1e6),
    "fy": Number(1.0, 1e6),
    "cx": Number(-1e5, 1e5),
    "cy": Number(-1e5, 1e5),
    "distortion": Tuple.of(Number(-100.0, 100.0), 5, doc="OpenCV's k1, k2, p1, p2, k3"),
})
_CAMERA = Section({
    "id": Id(),
    "kind": Choice(("phone", "depth")),
    "intrinsics": _INTRINSICS,
    "beam_from_camera": _POSE,
})
_BEAM_POSE = Section({
    "angle_index": Integer(0, 10_000),
    "encoder_deg": Number(-720.0, 720.0),
    "angle_deg": Number(-720.0, 720.0, doc="calibrated"),
    "tilt_deg": Tuple.of(Number(-10.0, 10.0), 2, doc="the beam's wobble about x and y"),
    "shift_mm": Tuple.of(Number(-100.0, 100.0), 3),
})
_RESIDUALS = Section({
    "count": Integer(0, 1e12),
    "discarded": Integer(0, 1e12),
    "mean_px": Number(0.0),
    "median_px": Number(0.0),
    "rms_px": Number(0.0),
    "p95_px": Number(0.0),
    "max_px": Number(0.0),
    "per_camera_mean_px": Nullable(MapOf(Id(), Number(0.0))),
    "per_camera_count": Nullable(MapOf(Id(), Integer(0, 1e12))),
})
_LONG_TEXT = 4096  # a source names a folder

CALIBRATION_FILE = ConfigFile(
    what="calibration file",
    where="calibration.yaml beside the rig file (the rig file's calibration.file), written by tbp calibrate",
    max_bytes=16 * 1024 * 1024,  # a calibration file of the default rig (10 cameras, 96 captures) is ~60 KB
    table=Section({
        "format": Choice((CALIBRATION_FORMAT,)),
        "created_utc": Text(max_len=_LONG_TEXT),
        "rig_digest": Nullable(Text(min_len=0, max_len=_LONG_TEXT), doc="SHA-256 of the rig file calibrated"),
        "target": Text(max_len=_LONG_TEXT),
        "source": Text(max_len=_LONG_TEXT),
        "cameras": ListOf(_CAMERA, 1, 256),
        "beam": ListOf(_BEAM_POSE, 0, 10_000, doc="the beam at each capture"),
        "world_from_cuboid": _POSE,
        "cuboid_from_boards": ListOf(_POSE, 0, 64),
        "residuals": Nullable(_RESIDUALS, doc="reprojection residuals of the final bundle adjustment"),
    }, doc="every camera's lens and pose on the beam, the beam's pose at every capture"),
    rules=("camera ids are unique",),
)

# ---------------------------------------------------------------------------- calibration target

CUBOID_FACES = ("+x", "+y", "-x", "-y")

TARGET_FILE = ConfigFile(
    what="target file",
    where="calibration_data/target/cuboid.yaml",
    max_bytes=1024 * 1024,
    table=Section({
        "name": Text(),
        "size_mm": Tuple.of(Number(10.0, 5000.0), 3, doc="x, y, z"),
        "dictionary": Text(pattern=re.compile(r"DICT_[A-Z0-9_]{1,40}"),
                           shape="an OpenCV predefined ArUco dictionary such as DICT_5X5_1000"),
        "legacy_pattern": Flag(doc="OpenCV's layout before 4.6 (only matters for an even row count)"),
        "squares": Tuple.of(Integer(3, 200), 2, doc="columns across the face, rows up the face"),
        "square_mm": Number(1.0, 1000.0, doc="measured on the print: the calibration's metric scale"),
        "marker_mm": Number(0.5, 1000.0),
        "print_dpi": Integer(50, 1200),
        "faces": ListOf(Section({
            "name": Choice(CUBOID_FACES, doc="the face's outward normal"),
            "first_marker_id": Integer(0, 100_000),
        }), 1, 4),
    }, doc="the ChArUco calibration cuboid"),
    rules=("dictionary is one OpenCV has", "marker_mm is smaller than square_mm",
           "each face's marker ids lie in the dictionary and overlap no other face's; no face appears twice",
           "the board fits its face"),
)

# ---------------------------------------------------------------------------- focus table

MIN_DISTANCE_MM = 20.0
MAX_DISTANCE_MM = 100_000.0
MAX_DIOPTERS = 50.0

FOCUS_FILE = ConfigFile(
    what="focus table",
    where="calibration_data/focus/*.yaml, named by the rig file's phones[].focus_calibration",
    max_bytes=1024 * 1024,  # a focus table is a few hundred bytes
    table=Section({
        "points": ListOf(Tuple((Number(0.0, MAX_DIOPTERS), Number(MIN_DISTANCE_MM, MAX_DISTANCE_MM))), 2, 1000,
                         doc="[commanded diopters, sharpest distance mm]"),
        "phone_model": Note(default=None),
        "measured": Note(default=None, doc="when and how"),
    }, doc="a phone's commanded LENS_FOCUS_DISTANCE -> measured sharpest distance"),
    rules=("commanded diopters strictly increase and the distances strictly decrease",),
)

# ---------------------------------------------------------------------------- hardware file

CAN_INTERFACES = ("socketcan", "slcan", "socketcand", "virtual")
HOST_PORT = re.compile(r"(?P<host>[A-Za-z0-9.-]{1,253}|\[[0-9A-Fa-f:]{2,39}\]):(?P<port>[0-9]{1,5})")
PHONE_LINKS: dict[str, Kind] = {
    "usb": Kind(Nullable(Serial()), bare=True,
                doc="over USB, found by the rig file's serial; {usb: SERIAL} only with that serial"),
    "tcp": Kind(Text(pattern=HOST_PORT, max_len=260, shape="HOST:PORT, e.g. 192.168.50.11:5555"),
                doc="ADB over TCP (wireless debugging)"),
}


def hardware_file(depth_kinds: Mapping[str, Kind]) -> ConfigFile:
    """The hardware file's table, its depth cameras reached in one of ``depth_kinds`` (the device
    registry's table: kind name -> the form of its value in the file)."""
    return ConfigFile(
        what="hardware file",
        where="hardware.yaml beside the rig file; on a rig PC /etc/tbp-rig/hardware.yaml",
        max_bytes=256 * 1024,
        table=Section({
            "can": Section({
                "interface": Choice(CAN_INTERFACES),
                "channel": Text(),
                "host": Text(default=None, doc="socketcand's bridge"),
                "port": Integer(1, 65535, default=None, doc="socketcand's bridge"),
                "bitrate": Integer(10_000, 1_000_000, default=None, doc="slcan only (set by the OS otherwise)"),
            }, doc="the beam drive's bus (python-can)"),
            "phones": MapOf(Id(), Kinds(PHONE_LINKS), 64, doc="every phone of the rig file, by its id"),
            "depth_cameras": MapOf(Id(), Kinds(depth_kinds), 16, doc="every depth camera of the rig file, by its id"),
            "panel": Nullable(Section({"device": Text(), "baud": Integer(1200, 4_000_000, default=115200)}),
                              doc="the operator panel's serial port; null: a rig without a panel"),
            "capture_agent": Nullable(Text(), default=None, doc="the capture agent's jar, pushed to phones without it"),
            "timeouts": Section({
                "open_s": Number(0.5, 120.0, default=5.0, doc="each device's open (connect, handshake)"),
                "phone_authorisation_s": Number(1.0, 600.0, default=60.0,
                                                doc="a phone's first connection, while someone accepts the prompt"),
                "reprobe_s": Number(0.2, 60.0, default=2.0, doc="how often a missing device is tried again"),
            }, optional=True),
        }, doc="how this PC reaches every device of the rig file"),
        rules=("phones and depth_cameras name exactly the rig file's devices",
               "a serial written in the file is the rig file's",
               "socketcand has a host and port, the other interfaces none; only slcan has a bitrate",
               "relative paths are relative to the hardware file"),
    )


# ---------------------------------------------------------------------------- site file

AE_TITLE = re.compile(r"(?=.*[^ ])[ -\[\]-~]{1,16}")
"""An AE title: 1-16 characters of DICOM's default repertoire, no backslash, not only spaces."""
AE = Text(pattern=AE_TITLE, max_len=16, shape="an AE title: 1-16 printable ASCII characters, no backslash")
URL = re.compile(r"https?://[^\s]+")


def _peer(**more: Node) -> Section:
    return Section({"host": Text(max_len=253), "port": Integer(1, 65535),
                    "called_aet": Text(pattern=AE_TITLE, max_len=16, shape=AE.shape, doc="the peer's AE title"),
                    **more})


SITE_FILE = ConfigFile(
    what="site file",
    where="site.yaml beside the rig file; on a rig PC /etc/tbp-rig/site.yaml",
    max_bytes=64 * 1024,
    table=Section({
        "ae_title": Text(pattern=AE_TITLE, max_len=16, shape=AE.shape,
                         doc="this rig's AE title: the calling AE of every association"),
        "worklist": Nullable(_peer(
            modality=Text(max_len=16, default="XC", doc="the scheduled steps asked for (XC: external-camera photography)"),
            station_aet=Nullable(AE, default=None, doc="only steps scheduled on this station"),
        ), default=None, doc="the Modality Worklist provider (C-FIND); null: none"),
        "archive": Nullable(Section({
            "pacs": Nullable(_peer(), default=None, doc="a PACS over C-STORE"),
            "dicomweb": Nullable(Text(pattern=URL, max_len=2048, shape="an http:// or https:// URL"), default=None,
                                 doc="a DICOMweb service (STOW-RS)"),
            "deidentify": Flag(default=False, doc="PS3.15's basic profile (research archives)"),
            "retry": Section({
                "first_s": Number(0.1, 3600.0, default=10.0, doc="the first wait after an outage"),
                "max_s": Number(1.0, 86400.0, default=600.0, doc="the wait doubles up to this"),
            }, optional=True),
        }), default=None, doc="where the daemon exports every completed scan; null: nowhere"),
        "tls": Nullable(Section({
            "ca_file": Text(doc="the clinic's CA"),
            "cert_file": Nullable(Text(), default=None, doc="this rig's certificate (mutual TLS)"),
            "key_file": Nullable(Text(), default=None, doc="its key"),
        }), default=None, doc="DICOM over TLS for the archive and the worklist; null: plain TCP"),
    }, doc="how this rig reaches the clinic's DICOM services"),
    rules=("archive names exactly one of pacs and dicomweb",
           "archive.retry.max_s is at least first_s",
           "relative paths are relative to the site file"),
)
