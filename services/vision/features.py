"""Image features of the AprilTag target, as plain functions (OpenCV for detection and pose).

Corner order is the detection order of :mod:`services.model.tag` (top-left, top-right, bottom-right,
bottom-left of the upright tag). Normalized image coordinates are x = X/Z, y = Y/Z in OpenCV's optical frame.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import cv2
import numpy as np

from protocol.messages import FeatureStatus
from services.model import frames
from services.model.point_features import feature_error
from services.model import tag as tags
from services.runtime.config import ConfigStruct


class Backend(str, enum.Enum):
    """The detector. ``apriltag``: the AprilTag project's own detector (AprilTag 3, through pupil-apriltags): on
    rendered frames its corners are within 0.45 px of the true projection from 0.2 to 3 m at tilts up to 60°.
    ``aruco``: OpenCV's aruco with a corner ``Refinement``: within 0.35 px up to 1.5 m facing the camera, but its
    refinement moves the corners of small tags by 2-4.5 px beyond 2 m and it loses a 60°-tilted tag at 2.5 m."""

    APRILTAG = "apriltag"
    ARUCO = "aruco"


class Refinement(str, enum.Enum):
    """Corner refinement. With ``aruco``: ``apriltag_subpix`` (its default): aruco's AprilTag refinement, then
    OpenCV's sub-pixel corner search; on rendered frames its corners are within 0.35 px of the true projection,
    against 0.6-0.9 px for aruco's AprilTag refinement alone. With ``apriltag``: ``subpix`` (or
    ``apriltag_subpix``): the library's quads, then the same sub-pixel search, which lands on aruco's
    ``apriltag_subpix`` corners (within 0.001 px where aruco's are good) in a quarter of the time; ``none`` (or
    ``apriltag``, its default): the library's corners as they come (closest to the truth far away and tilted, but
    at close range their errors are uneven enough to tilt a frontal tag's pose by 4°: docs/vision.md)."""

    APRILTAG_SUBPIX = "apriltag_subpix"
    APRILTAG = "apriltag"
    SUBPIX = "subpix"
    CONTOUR = "contour"
    NONE = "none"


_ARUCO_METHOD = {
    Refinement.APRILTAG_SUBPIX: cv2.aruco.CORNER_REFINE_APRILTAG,
    Refinement.APRILTAG: cv2.aruco.CORNER_REFINE_APRILTAG,
    Refinement.SUBPIX: cv2.aruco.CORNER_REFINE_SUBPIX,
    Refinement.CONTOUR: cv2.aruco.CORNER_REFINE_CONTOUR,
    Refinement.NONE: cv2.aruco.CORNER_REFINE_NONE,
}
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


#: the bit errors the AprilTag library corrects in a tag's code by default (apriltag_detector_add_family)
APRILTAG_CORRECTED_BITS = 2


def _apriltag_detector(family: str, quad_decimate: float, corrected_bits: int = APRILTAG_CORRECTED_BITS):
    """The AprilTag library's detector (pupil-apriltags), torn down in the right order: pupil-apriltags 1.0.4
    frees the tag families before the detector that still points at them (apriltag_detector_destroy then reads
    freed memory: an intermittent segfault, pupil-labs/apriltags#46; the order duckietown/lib-dt-apriltags#26
    fixed).

    ``corrected_bits``: a tag read with up to this many wrong cells still decodes. The library decodes through a
    table of every code with that many bits flipped: for tag36h11 36 MB at 2 bits (its default, the only value
    pupil-apriltags passes), 1 MB at 1 bit, 28 kB at 0 (apriltag 3.1's sizes: it allots permutations where
    combinations do, fixed upstream in AprilRobotics/apriltag#414). Another value rebuilds the family's table
    (the 2-bit one is freed)."""
    if not 0 <= corrected_bits <= APRILTAG_CORRECTED_BITS:
        raise ValueError(f"apriltag corrected bits must be 0 to {APRILTAG_CORRECTED_BITS}, not {corrected_bits}")
    from pupil_apriltags import Detector

    class OrderedTeardownDetector(Detector):
        def __del__(self) -> None:
            if getattr(self, "tag_detector_ptr", None) is None:
                return
            self.libc.apriltag_detector_destroy.restype = None
            self.libc.apriltag_detector_destroy(self.tag_detector_ptr)
            self.tag_detector_ptr = None
            for name, tag_family in self.tag_families.items():
                destroy = getattr(self.libc, f"{name}_destroy")
                destroy.restype = None
                destroy(tag_family)

    detector = OrderedTeardownDetector(families=family, nthreads=1, quad_decimate=quad_decimate, refine_edges=1)
    if corrected_bits != APRILTAG_CORRECTED_BITS:
        libc, tag_family = detector.libc, detector.tag_families[family]
        libc.apriltag_detector_remove_family.restype = None  # frees the family's decode table
        libc.apriltag_detector_remove_family(detector.tag_detector_ptr, tag_family)
        libc.apriltag_detector_add_family_bits(detector.tag_detector_ptr, tag_family, corrected_bits)
    return detector


@dataclass
class Detection:
    tag_id: int
    #: 4×2 pixel coordinates in detection order
    corners_px: np.ndarray


class TagDetector:
    """Detects tags of one family in grayscale images; corners in the printed image's order (``layout``)."""

    def __init__(self, family: str = "tag36h11", refinement: Refinement | str | None = None,
                 subpix_window: int = 3, layout: tags.TagLayout | str = tags.TagLayout.OFFICIAL,
                 backend: Backend | str = Backend.ARUCO, quad_decimate: float = 1.0,
                 apriltag_corrected_bits: int = APRILTAG_CORRECTED_BITS) -> None:
        self.backend = Backend(backend)
        if refinement is None:  # each backend's own
            refinement = Refinement.APRILTAG if self.backend is Backend.APRILTAG else Refinement.APRILTAG_SUBPIX
        self.refinement = Refinement(refinement)
        self.family = family
        #: which image of the tag is printed: the corners come in that image's order (services.model.tag)
        self.layout = tags.TagLayout(layout)
        self._subpix_window = subpix_window
        #: the sub-pixel corner search after detection
        self._subpix = self.refinement is Refinement.APRILTAG_SUBPIX or (
            self.backend is Backend.APRILTAG and self.refinement is Refinement.SUBPIX)
        if self.backend is Backend.APRILTAG:
            if self.refinement is Refinement.CONTOUR:
                raise ValueError("refinement contour is aruco's; the apriltag detector takes subpix or none")
            # one thread: the services share two cores; no decimation by default: a 3-m tag is 20 px wide
            self._apriltag = _apriltag_detector(family, quad_decimate, apriltag_corrected_bits)
            return
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = _ARUCO_METHOD[self.refinement]
        params.cornerRefinementWinSize = subpix_window
        self._detector = cv2.aruco.ArucoDetector(tags.dictionary(family), params)

    def detect(self, gray: np.ndarray, roi: tuple[int, int, int, int] | None = None) -> list[Detection]:
        """Every tag in ``gray``, or in its window ``roi`` = (x0, y0, x1, y1) (corners in full-image pixels)."""
        x0, y0 = (0, 0) if roi is None else roi[:2]
        window = gray if roi is None else gray[y0 : roi[3], x0 : roi[2]]
        if self.backend is Backend.APRILTAG:
            return self._detect_apriltag(window, x0, y0, gray)
        corners, ids, _ = self._detector.detectMarkers(window)
        if ids is None:
            return []
        out = []
        for tag_corners, tag_id in zip(corners, ids.ravel(), strict=True):
            c = (tag_corners.reshape(4, 2) + np.array([x0, y0], dtype=np.float32)).astype(np.float32)
            if self._subpix:
                c = self._refined(gray, c)
            if self.layout is tags.TagLayout.OFFICIAL:
                c = tags.official_order(c, self.family)
            out.append(Detection(int(tag_id), c.astype(float)))
        return out

    def _refined(self, gray: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """OpenCV's sub-pixel corner search from ``corners`` (4×2), on the whole image."""
        w = self._subpix_window
        start = np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2)
        return cv2.cornerSubPix(gray, start, (w, w), (-1, -1), _SUBPIX_CRITERIA).reshape(4, 2)

    def _detect_apriltag(self, window: np.ndarray, x0: int, y0: int, gray: np.ndarray) -> list[Detection]:
        out = []
        for found in self._apriltag.detect(np.ascontiguousarray(window, dtype=np.uint8)):
            # AprilTag's corners go counter-clockwise from the official image's bottom-left, in coordinates whose
            # pixel centres are at +0.5 (OpenCV's are at the pixel index)
            c = np.asarray(found.corners, dtype=float)[[3, 2, 1, 0]] + np.array([x0 - 0.5, y0 - 0.5])
            if self._subpix:
                c = self._refined(gray, c).astype(float)
            if self.layout is tags.TagLayout.OPENCV:
                c = tags.opencv_order(c, self.family)
            out.append(Detection(int(found.tag_id), c))
        return out

    def find(self, gray: np.ndarray, tag_id: int, roi: tuple[int, int, int, int] | None = None) -> Detection | None:
        """The tag with ``tag_id`` (the largest, if several carry that id), in the whole image or in ``roi``."""
        matches = [d for d in self.detect(gray, roi) if d.tag_id == tag_id]
        if not matches:
            return None
        return max(matches, key=lambda d: abs(cv2.contourArea(d.corners_px.astype(np.float32))))


class RoiConfig(ConfigStruct):
    """Detection in a window around the tag's last corners (full-frame detection costs 8-13 ms at 640×480 here,
    most of it thresholding and contour search over pixels far from the tag)."""

    enabled: bool = True
    #: the window is the last corners' bounding box grown by this fraction of its size on every side ...
    margin_fraction: float = 0.25
    #: ... and by at least this many pixels (the tag's motion between frames: 0.8 rad/s at 30 Hz is ~16 px)
    min_margin_px: int = 48
    #: a full-frame detection every this many frames all the same (a larger tag with the same id elsewhere)
    full_frame_every: int = 30

    def __post_init__(self) -> None:
        if not (0.0 <= self.margin_fraction <= 4.0 and 8 <= self.min_margin_px <= 1000 and self.full_frame_every >= 1):
            raise ValueError("roi needs 0 <= margin_fraction <= 4, 8 <= min_margin_px <= 1000, full_frame_every >= 1")


class TagTracker:
    """Finds one tag frame after frame: in a window around where it was last seen (:class:`RoiConfig`), falling
    back to the full frame when it is not there, and on the full frame every ``full_frame_every`` frames. A pure
    core (no clock, no I/O): the same frames give the same corners. The window's detection keeps the full frame's
    accuracy: the detector's thresholds are local (windows of at most 23 px) and the margin is wider, and the
    sub-pixel refinement runs on the full image."""

    def __init__(self, detector: "TagDetector", config: RoiConfig | None = None) -> None:
        self.detector = detector
        self.config = config or RoiConfig()
        self.last_corners_px: np.ndarray | None = None
        self._since_full = 0
        #: how each frame was searched: ``window``, ``full`` (none to track, or the periodic one) and ``fallback``
        #: (the window missed it)
        self.searches = {"window": 0, "full": 0, "fallback": 0}
        self.last_search = ""

    def window(self, shape: tuple[int, ...]) -> tuple[int, int, int, int] | None:
        """(x0, y0, x1, y1) of the next search, or None for the full frame."""
        cfg = self.config
        if not cfg.enabled or self.last_corners_px is None or self._since_full >= cfg.full_frame_every:
            return None
        height, width = shape[:2]
        lo, hi = self.last_corners_px.min(axis=0), self.last_corners_px.max(axis=0)
        margin = np.maximum(cfg.min_margin_px, cfg.margin_fraction * (hi - lo))
        x0, y0 = np.floor(np.maximum(lo - margin, 0)).astype(int)
        x1, y1 = np.ceil(np.minimum(hi + margin + 1, (width, height))).astype(int)
        if x1 - x0 >= width and y1 - y0 >= height:
            return None
        return int(x0), int(y0), int(x1), int(y1)

    def find(self, gray: np.ndarray, tag_id: int) -> "Detection | None":
        roi = self.window(gray.shape)
        found = None
        if roi is not None:
            found = self.detector.find(gray, tag_id, roi=roi)
            self.last_search = "window" if found is not None else "fallback"
            self._since_full += 1
        if found is None:
            found = self.detector.find(gray, tag_id)
            self._since_full = 0
            if roi is None:
                self.last_search = "full"
        self.searches[self.last_search] += 1
        self.last_corners_px = None if found is None else found.corners_px
        return found

    def take_last_search(self) -> str:
        """How the last :meth:`find` searched (``window``, ``full``, ``fallback``), once; "" if none since."""
        search, self.last_search = self.last_search, ""
        return search


def camera_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def normalize(corners_px: np.ndarray, K: np.ndarray, distortion: np.ndarray | None = None) -> np.ndarray:
    """Pixel → normalized image coordinates (undistorted when distortion coefficients are given)."""
    pts = np.asarray(corners_px, dtype=np.float64).reshape(-1, 1, 2)
    dist = None if distortion is None or not np.any(distortion) else np.asarray(distortion, dtype=np.float64)
    return cv2.undistortPoints(pts, K, dist).reshape(-1, 2)


def tag_pose(corners_px: np.ndarray, K: np.ndarray, distortion: np.ndarray | None, size_m: float):
    """(R, t) of the tag in the camera frame by solvePnP with IPPE_SQUARE on the known tag size."""
    dist = None if distortion is None or not np.any(distortion) else np.asarray(distortion, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(tags.corners_in_tag(size_m), np.asarray(corners_px, dtype=np.float64), K, dist,
                                  flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok:
        raise ValueError("solvePnP found no pose for the tag corners")
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec.ravel()


def corners_in_camera(T_camera_tag: np.ndarray, size_m: float) -> np.ndarray:
    """4×3 corner positions in the camera frame for the tag at pose T (tag in camera)."""
    return (T_camera_tag[:3, :3] @ tags.corners_in_tag(size_m).T).T + T_camera_tag[:3, 3]


def project(points_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normalized points n×2, depths n) of points in the camera frame; raises if a point is not in front."""
    points_camera = np.asarray(points_camera, dtype=float)
    depths = points_camera[:, 2]
    if np.any(depths <= 1e-6):
        raise ValueError("a tag corner is not in front of the camera")
    return points_camera[:, :2] / depths[:, None], depths


def goal_from_camera_in_tag(T_tag_camera: np.ndarray, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Desired features and depths for the camera at pose T_tag_camera (camera in the tag frame)."""
    return project(corners_in_camera(np.linalg.inv(T_tag_camera), size_m))


def touches_border(corners_px: np.ndarray, width: int, height: int, margin_px: float) -> bool:
    c = np.asarray(corners_px)
    return bool(np.any(c[:, 0] < margin_px) or np.any(c[:, 1] < margin_px)
                or np.any(c[:, 0] > width - 1 - margin_px) or np.any(c[:, 1] > height - 1 - margin_px))


@dataclass
class Measurement:
    """What one grayscale image says about the tag: a status, a reason when it is not ``ok``, and for ``ok`` or
    ``partial`` the features, their depths, the error against the goal and the tag's pose."""

    status: FeatureStatus
    detail: str = ""
    #: the image was unusable or the pose implausible (counted as a rejection), rather than the tag out of view
    rejected: bool = False
    points: np.ndarray | None = None
    depths: np.ndarray | None = None
    error: np.ndarray | None = None
    error_norm: float = 0.0
    #: the tag's pose in the camera frame (R, t)
    pose: tuple[np.ndarray, np.ndarray] | None = None
    corners_px: np.ndarray | None = None


def measure(gray: np.ndarray, detector: TagDetector, tag_id: int, size_m: float, K: np.ndarray,
            distortion: np.ndarray | None, goal_points: np.ndarray, min_peak_brightness: int = 0,
            border_margin_px: float = 0.0) -> Measurement:
    """Detect → normalise → pose → error for one image: vision's rules, with no zenoh, clock or lock."""
    if int(gray.max()) < min_peak_brightness:
        return Measurement(FeatureStatus.INVALID_IMAGE, "all-black image", rejected=True)
    detection = detector.find(gray, tag_id)
    if detection is None:
        return Measurement(FeatureStatus.TARGET_LOST, f"tag {tag_id} not in view")
    points = normalize(detection.corners_px, K, distortion)
    R, t = tag_pose(detection.corners_px, K, distortion, size_m)
    depths = corners_in_camera(frames.homogeneous(R, t), size_m)[:, 2]
    if np.any(depths <= 0):
        return Measurement(FeatureStatus.TARGET_LOST, "implausible tag pose: a corner behind the camera", rejected=True)
    error, norm = feature_error(points, goal_points)
    height, width = gray.shape[:2]
    partial = touches_border(detection.corners_px, width, height, border_margin_px)
    return Measurement(FeatureStatus.PARTIAL if partial else FeatureStatus.OK,
                       "tag touches the image border" if partial else "",
                       points=points, depths=depths, error=error, error_norm=norm, pose=(R, t),
                       corners_px=detection.corners_px)
