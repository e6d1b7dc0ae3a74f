"""A scan folder as one DICOM study: the instances an export sends, made one at a time.

* every verified image: **VL Photographic Image** (1.2.840.10008.5.1.4.1.1.77.1.4), the phone's
  JPEG carried unchanged in JPEG Baseline (1.2.840.10008.1.2.4.50), its acquisition context
  (camera, planned and actual exposure angle, focus distance, skin resolution at that distance,
  camera position and optical axis in the rig frame) as Acquisition Context items, and
  Recognizable Visual Features YES where the face may be in the picture;
* the body mesh: **Encapsulated STL** (1.2.840.10008.5.1.4.1.1.104.3), binary STL in mm;
* each lesion mark: a **Key Object Selection** document (1.2.840.10008.5.1.4.1.1.88.59) titled
  "Of Interest", pointing at the mark's best image, its name and point as the description;
* the QA report: a **Basic Text SR** (1.2.840.10008.5.1.4.1.1.88.11) of the report's figures.

Every UID is derived from the scan's Study Instance UID and the thing it names (the image file, the
mark id), so exporting the same scan again makes the same instances: an archive that has them
adds nothing. A de-identified export (archive/deidentify.py) derives another set from those.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from analysis.scan_views import ScanRecord, open_scan
from daemon.clinic.patient import derived_uid
from daemon.errors import DaemonError
from daemon.records.manifest import ImageRecord, ImageStatus

VL_PHOTOGRAPHIC = "1.2.840.10008.5.1.4.1.1.77.1.4"
ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"
KEY_OBJECT_SELECTION = "1.2.840.10008.5.1.4.1.1.88.59"
BASIC_TEXT_SR = "1.2.840.10008.5.1.4.1.1.88.11"
JPEG_BASELINE = "1.2.840.10008.1.2.4.50"
EXPLICIT_LE = "1.2.840.10008.1.2.1"
SOFTWARE = "tbp-rig 0.1.0"
CODING = "99TBP"
"""This project's private coding scheme for the acquisition context's concepts."""
FACE_BAND_MM = 260.0
"""The head: the top of the body down to this far (the face lies inside it)."""


class ExportError(DaemonError):
    """A scan cannot be exported as it is; names the scan folder and the reason."""

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


@dataclass(frozen=True)
class Instance:
    """One instance of the study, made on demand (an image's JPEG is read only then)."""

    kind: str
    """image, mesh, mark or report"""
    name: str
    """What it is, for messages: the image file, "mesh", the mark id, "QA report"."""
    sop_class_uid: str
    sop_instance_uid: str
    transfer_syntax: str
    make: Callable[[], Any]


def _code(value: str, scheme: str, meaning: str) -> Any:
    from pydicom.dataset import Dataset

    code = Dataset()
    code.CodeValue, code.CodingSchemeDesignator, code.CodeMeaning = value, scheme, meaning
    return code


def _stamp(created_utc: str) -> tuple[str, str]:
    """(DA, TM) of the scan's start (UTC)."""
    try:
        when = datetime.fromisoformat(created_utc)
    except ValueError:
        return "", ""
    return f"{when:%Y%m%d}", f"{when:%H%M%S}"


class StudyBuilder:
    """The instances of one scan folder's study. ``rig_path``: the rig file the scan was taken
    with (default the installed one)."""

    def __init__(self, folder: Path | str, rig_path: Path | str | None = None) -> None:
        self.path = Path(folder)
        self.record: ScanRecord = open_scan(self.path, rig_path)
        m = self.record.manifest
        if m.in_progress:
            raise ExportError(self.path, "the scan is still in progress")
        if m.patient is None or m.study is None:
            raise ExportError(self.path, "the scan is for no patient: only a de-identified export can send it")
        self.manifest = m
        self.patient = m.patient
        self.study = m.study
        self.date, self.time = _stamp(m.created_utc)
        self._poses: Any = None
        self._faces: np.ndarray | None = None
        self.report_scan_id = True
        """The QA report names the scan id (a de-identified export leaves it out)."""

    # ------------------------------------------------------------------ identities

    def uid(self, *parts: str) -> str:
        return derived_uid("instance", self.study.study_instance_uid, *parts)

    def series_uid(self, kind: str) -> str:
        return self.study.series_instance_uid if kind == "image" else self.uid("series", kind)

    SERIES = {"image": (1, "XC", "Total body photographs"), "mesh": (2, "M3D", "Body surface"),
              "mark": (3, "KO", "Lesion marks"), "report": (4, "SR", "Scan QA report")}

    def _common(self, kind: str, sop_class: str, sop_uid: str, number: int) -> Any:
        """Patient, General Study, General Series, General Equipment and SOP Common."""
        from pydicom.dataset import Dataset

        p, s = self.patient, self.study
        ds = Dataset()
        ds.SpecificCharacterSet = "ISO_IR 192"
        ds.SOPClassUID, ds.SOPInstanceUID = sop_class, sop_uid
        ds.PatientName, ds.PatientID = p.name, p.patient_id
        ds.PatientBirthDate, ds.PatientSex = p.birth_date or "", p.sex or ""
        ds.StudyInstanceUID, ds.StudyDate, ds.StudyTime = s.study_instance_uid, self.date, self.time
        ds.ReferringPhysicianName, ds.StudyID = "", self.manifest.scan_id[:16]
        ds.AccessionNumber, ds.StudyDescription = s.accession_number or "", s.description
        series_number, modality, description = self.SERIES[kind]
        ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber = modality, self.series_uid(kind), series_number
        ds.SeriesDescription, ds.SeriesDate, ds.SeriesTime = description, self.date, self.time
        ds.Manufacturer, ds.ManufacturerModelName, ds.SoftwareVersions = "tbp-rig", "TBP rig", SOFTWARE
        ds.DeviceSerialNumber = self.manifest.rig_digest[:16] or "unknown"
        ds.InstanceNumber, ds.ContentDate, ds.ContentTime = number, self.date, self.time
        return ds

    # ------------------------------------------------------------------ the study

    def instances(self) -> list[Instance]:
        """Every instance of the study: images, mesh, marks, QA report (in that order)."""
        out = []
        images = self.images()
        for n, image in enumerate(images, 1):
            out.append(Instance("image", image.file or "", VL_PHOTOGRAPHIC, self.uid("image", image.file or ""),
                                JPEG_BASELINE, lambda image=image, n=n: self.image_dataset(image, n)))
        if "mesh" in self.manifest.files:
            out.append(Instance("mesh", "mesh", ENCAPSULATED_STL, self.uid("mesh"), EXPLICIT_LE, self.mesh_dataset))
        for n, mark in enumerate(self.marks(), 1):
            out.append(Instance("mark", mark.id, KEY_OBJECT_SELECTION, self.uid("mark", mark.id), EXPLICIT_LE,
                                lambda mark=mark, n=n: self.mark_dataset(mark, n)))
        out.append(Instance("report", "QA report", BASIC_TEXT_SR, self.uid("report"), EXPLICIT_LE, self.report_dataset))
        return out

    def images(self) -> list[ImageRecord]:
        return [i for i in self.record.images if i.status is ImageStatus.VERIFIED and self.record.image_on_disk(i)]

    def marks(self) -> list[Any]:
        from analysis.marks import MarkError, read_marks

        try:
            return read_marks(self.path).marks
        except MarkError as exc:
            raise ExportError(self.path, f"marks: {exc}") from exc

    # ------------------------------------------------------------------ images

    def poses(self) -> Any:
        if self._poses is None:
            self._poses = self.record.poses()
        return self._poses

    def image_dataset(self, image: ImageRecord, number: int) -> Any:
        """VL Photographic Image with the JPEG unchanged (JPEG Baseline)."""
        from pydicom.encaps import encapsulate

        path = self.path / (image.file or "")
        data = path.read_bytes()
        rows, columns, photometric = jpeg_frame(data, path)
        ds = self._common("image", VL_PHOTOGRAPHIC, self.uid("image", image.file or ""), number)
        ds.ImageType = ["ORIGINAL", "PRIMARY"]
        ds.PatientOrientation = ""
        ds.AcquisitionDateTime = f"{self.date}{self.time}"
        ds.BurnedInAnnotation = "NO"
        ds.RecognizableVisualFeatures = "YES" if self.shows_face(image) else "NO"
        ds.LossyImageCompression, ds.LossyImageCompressionMethod = "01", "ISO_10918_1"
        ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, photometric, 0
        ds.Rows, ds.Columns = rows, columns
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 8, 8, 7, 0
        ds.AnatomicRegionSequence = [_code("38266002", "SCT", "Entire body")]
        ds.AcquisitionContextSequence = self.acquisition_context(image)
        ds.ImageComments = f"{image.camera_id} at {image.actual_angle_deg or image.planned_angle_deg:.2f} deg"
        ds.PixelData = encapsulate([data])
        ds["PixelData"].VR = "OB"
        ds["PixelData"].is_undefined_length = True  # encapsulated: items, then a sequence delimiter
        return ds

    def acquisition_context(self, image: ImageRecord) -> list[Any]:
        from pydicom.dataset import Dataset

        rig = self.record.rig
        pose = rig.pose_index(image.angle_index, image.camera_index)
        poses = self.poses()
        mm_per_px = image.focus_mm * 2 * np.tan(np.radians(rig.optics.hfov_deg) / 2) / rig.optics.image_width_px
        items: list[Any] = []

        def text(code: str, meaning: str, value: str) -> None:
            item = Dataset()
            item.ValueType, item.ConceptNameCodeSequence, item.TextValue = "TEXT", [_code(code, CODING, meaning)], value
            items.append(item)

        def number(code: str, meaning: str, value: float | None, unit: tuple[str, str]) -> None:
            if value is None or not np.isfinite(value):
                return
            item = Dataset()
            item.ValueType, item.ConceptNameCodeSequence = "NUMERIC", [_code(code, CODING, meaning)]
            item.NumericValue = f"{value:.6g}"
            item.MeasurementUnitsCodeSequence = [_code(unit[0], "UCUM", unit[1])]
            items.append(item)

        deg, mm = ("deg", "degree"), ("mm", "millimeter")
        text("camera", "Camera", image.camera_id)
        number("angle-index", "Capture angle index", float(image.angle_index), ("1", "no units"))
        number("angle", "Beam angle at exposure", image.actual_angle_deg, deg)
        number("planned", "Planned beam angle", image.planned_angle_deg, deg)
        number("focus", "Focus distance", image.focus_mm, mm)
        number("resolution", "Pixel size at focus distance", float(mm_per_px), ("mm/{pixel}", "millimeter per pixel"))
        for axis, value in zip("xyz", poses.centres[pose]):
            number(f"position-{axis}", f"Camera position {axis} (rig frame)", float(value), mm)
        for axis, value in zip("xyz", poses.forward[pose]):
            number(f"axis-{axis}", f"Optical axis {axis} (rig frame)", float(value), ("1", "no units"))
        return items

    def shows_face(self, image: ImageRecord) -> bool:
        """Whether the face may be in the picture: a point of the front of the head (the top
        FACE_BAND_MM of the body, the half facing +x, facing the camera) lands inside the image."""
        rig = self.record.rig
        faces = self.face_points()
        if len(faces) == 0:
            return True  # no body to tell by: flagged, as a face may be there
        poses = self.poses()
        pose = rig.pose_index(image.angle_index, image.camera_index)
        rel = faces - poses.centres[pose]
        depth = rel @ poses.forward[pose]
        focal = rig.optics.image_width_px / 2 / np.tan(np.radians(rig.optics.hfov_deg) / 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = rel @ poses.right[pose] / depth * focal + rig.optics.image_width_px / 2
            v = rel @ poses.down[pose] / depth * focal + rig.optics.image_height_px / 2
        inside = (depth > 0) & (u >= 0) & (u < rig.optics.image_width_px) & (v >= 0) & (v < rig.optics.image_height_px)
        return bool(inside.any())

    def face_points(self) -> np.ndarray:
        """(N, 3) mm: mesh vertices of the front of the head facing the front (+x)."""
        if self._faces is None:
            if "mesh" not in self.manifest.files:
                self._faces = np.zeros((0, 3))
            else:
                mesh = self.record.mesh()
                v, n = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
                head = v[:, 2] > v[:, 2].max() - FACE_BAND_MM
                centre = v[head].mean(axis=0) if head.any() else np.zeros(3)
                front = head & (v[:, 0] > centre[0]) & (n[:, 0] > 0.3)
                picked = np.flatnonzero(front)
                self._faces = v[picked[:: max(1, len(picked) // 400)]]
        return self._faces

    # ------------------------------------------------------------------ mesh, marks, report

    def mesh_dataset(self) -> Any:
        """Encapsulated STL: the reconstructed body surface, binary STL, mm in the rig frame."""
        ds = self._common("mesh", ENCAPSULATED_STL, self.uid("mesh"), 1)
        stl = self.record.mesh().export(file_type="stl")
        if len(stl) % 2:
            stl += b"\0"
        ds.FrameOfReferenceUID = self.uid("frame")
        ds.PositionReferenceIndicator = ""
        ds.AcquisitionDateTime = f"{self.date}{self.time}"
        ds.BurnedInAnnotation, ds.RecognizableVisualFeatures = "NO", "YES"
        ds.DocumentTitle = "Body surface from the depth sweep"
        ds.ConceptNameCodeSequence = []
        ds.MIMETypeOfEncapsulatedDocument = "model/stl"
        ds.EncapsulatedDocument = stl
        ds.EncapsulatedDocumentLength = len(stl)
        ds.MeasurementUnitsCodeSequence = [_code("mm", "UCUM", "millimeter")]
        return ds

    def best_image(self, point_mm: tuple[float, float, float]) -> ImageRecord | None:
        """The mark's best image (the viewer's and ``tbp navigate``'s ranking)."""
        from analysis.navigate import NavigationError, Navigator

        if not hasattr(self, "_navigator"):
            self._navigator = Navigator(self.record, self.record.mesh())
            self._navigator.prepare()
        try:
            views = self._navigator.query(point=np.asarray(point_mm, float), count=1)["views"]
        except NavigationError:
            return None
        if not views:
            return None
        return next((i for i in self.images() if i.file == views[0]["file"]), None)

    def mark_dataset(self, mark: Any, number: int, description: str | None = None) -> Any:
        """Key Object Selection "Of Interest" referencing the mark's best image."""
        from highdicom.ko import KeyObjectSelection, KeyObjectSelectionDocument
        from pydicom.sr.codedict import codes

        image = self.best_image(mark.point_mm)
        if image is None:
            raise ExportError(self.path, f"mark {mark.id}: no verified image sees its point")
        referenced = self._common("image", VL_PHOTOGRAPHIC, self.uid("image", image.file or ""), 0)
        text = description or f"{mark.name} at ({', '.join(f'{c:.1f}' for c in mark.point_mm)}) mm"
        document = KeyObjectSelectionDocument(
            evidence=[referenced],
            content=KeyObjectSelection(codes.DCM.OfInterest, [referenced], description=text[:1024]),
            series_instance_uid=self.series_uid("mark"), series_number=self.SERIES["mark"][0],
            sop_instance_uid=self.uid("mark", mark.id), instance_number=number, manufacturer="tbp-rig")
        document.SpecificCharacterSet = "ISO_IR 192"
        document.SeriesDescription = self.SERIES["mark"][2]
        document.StudyDescription = self.study.description
        return document

    def report_lines(self) -> list[tuple[str, str]]:
        """(heading, text) of the QA report's figures."""
        m = self.manifest
        counts = ", ".join(f"{k} {v}" for k, v in m.counts().items() if v)
        scan = f"{m.scan_id}: " if self.report_scan_id else ""
        lines = [("Scan", f"{scan}{m.state.value}" + (f" ({m.reason})" if m.reason else "")),
                 ("Images", counts)]
        plan = m.plan_summary or {}
        used = (plan.get("methods") or {}).get(plan.get("method"), {})
        if "in_focus_fraction" in used:
            lines.append(("Planned skin in focus", f"{100 * used['in_focus_fraction']:.1f} % ({plan.get('method')})"))
        qa = self.path / "qa.json"
        if qa.is_file():
            try:
                report = json.loads(qa.read_text())
            except ValueError:
                report = {}
            if report.get("max_abs_angle_error_deg") is not None:
                lines.append(("Exposure angle error", f"at most {report['max_abs_angle_error_deg']:.3f} deg"))
            if report.get("retaken") is not None:
                lines.append(("Retaken", f"{report['retaken']} images in the second pass"))
        problems = [i for i in m.images if i.status is not ImageStatus.VERIFIED]
        lines.append(("Missing or failed images", "none" if not problems else "; ".join(
            f"{i.camera_id} at {i.planned_angle_deg:.1f} deg: {i.status.value}" for i in problems[:50])))
        return lines

    def report_dataset(self) -> Any:
        """Basic Text SR: the QA report's figures as text, one item each."""
        from pydicom.dataset import Dataset

        ds = self._common("report", BASIC_TEXT_SR, self.uid("report"), 1)
        ds.ReferencedPerformedProcedureStepSequence = []
        ds.CompletionFlag, ds.VerificationFlag = "COMPLETE", "UNVERIFIED"
        ds.PerformedProcedureCodeSequence = []
        ds.ValueType, ds.ContinuityOfContent = "CONTAINER", "SEPARATE"
        ds.ConceptNameCodeSequence = [_code("qa-report", CODING, "Total body photography scan QA report")]
        items = []
        for heading, value in self.report_lines():
            item = Dataset()
            item.RelationshipType, item.ValueType = "CONTAINS", "TEXT"
            item.ConceptNameCodeSequence = [_code("qa-" + heading.lower().replace(" ", "-")[:12], CODING, heading)]
            item.TextValue = value[:10240]
            items.append(item)
        ds.ContentSequence = items
        return ds


def jpeg_frame(data: bytes, path: Path) -> tuple[int, int, str]:
    """(rows, columns, photometric interpretation) of a baseline 8-bit colour JPEG; ExportError for
    any other (a progressive or 12-bit JPEG cannot travel as JPEG Baseline unchanged)."""
    from PIL import Image, JpegImagePlugin, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.format != "JPEG" or im.mode != "RGB":
                raise ExportError(path, f"not an 8-bit colour JPEG ({im.format} {im.mode})")
            if im.info.get("progressive") or im.info.get("progression"):
                raise ExportError(path, "a progressive JPEG: JPEG Baseline carries only baseline ones")
            sampling = JpegImagePlugin.get_sampling(im)
            width, height = im.size
    except (UnidentifiedImageError, OSError) as exc:
        raise ExportError(path, f"unreadable JPEG: {exc}") from exc
    if b"\xff\xc0" not in data[:65536]:
        raise ExportError(path, "no baseline frame header (SOF0): JPEG Baseline carries only baseline JPEGs")
    return height, width, "YBR_FULL" if sampling == 0 else "YBR_FULL_422"


def study_file(instance: Instance) -> Any:
    """The instance as a DICOM file dataset (file meta information set), ready to save or send."""
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import UID

    ds = instance.make()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = UID(instance.transfer_syntax)
    ds.file_meta = meta
    return ds
