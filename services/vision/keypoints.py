"""The keypoint front end: a taught view's keypoints found again in each image, with no marker (Sensors 2022's own
future work: "markerless visual servoing in unstructured environments").

For each image, in turn (all OpenCV: SIFT or ORB, a brute-force matcher, USAC's MAGSAC, PnP, pyramidal LK):

1. **find** the taught keypoints: every ``detect_every`` frames (or when too few points are tracked) detect keypoints
   in a window around where the object was (the whole image when it was not seen) and match each taught descriptor
   to its two nearest (Lowe's ratio test, 0.75 as in CNS's front end); in between, **track** the points of the last
   frame with pyramidal Lucas-Kanade, kept only where the backward track returns within ``lk_back_px``;
2. **reject outliers robustly**: a homography between the taught and the current keypoints for a planar object
   (MAGSAC, ``cv2.USAC_MAGSAC``), the epipolar constraint (a fundamental matrix, MAGSAC) for a non-planar one. What
   OpenCV returns is not trusted as it comes: its mask can keep outliers (opencv#25546) and it returns a homography
   when the object is absent (opencv#4263), so the inliers are counted again here from our own reprojection
   (transfer) or Sampson errors, and a homography that mirrors the region or folds it is refused;
3. **the object's pose** by PnP on the inliers' taught 3D points (their depths measured at the teach), refined by
   Levenberg-Marquardt, and the reprojection error of every point under it: points over ``max_error_px`` are dropped,
   and the target is lost when fewer than ``min_inliers`` remain or their median error is over
   ``max_median_error_px``. Each point's depth is then its 3D point's under the pose (as a tag's corners' depths
   come from its pose);
4. **weigh** each point: by how well the object's pose explains it, Tukey's biweight of its reprojection error over
   the inliers' robust spread (1.4826 × their median absolute error, at least ``robust_floor_px``; c = 4.6851), as
   Comport, Marchand and Chaumette's robust visual servoing weighs its features (IEEE T-RO 22(2), 2006): a point
   the rigid object does not explain (a keypoint on the cup's silhouette, which slides along it as the view changes;
   one whose shading moved under another light) then pulls the arm less, so the servo settles where the object's
   consistent points put it; and by its **fade**: a point that joins the set comes with a weight rising to 1 over
   ``fade_frames``; a point that leaves it (occluded, out of view, rejected) is kept where the pose puts it, its
   weight falling to 0 over as many frames. The weighted law (services/controller/law.py) then changes its command
   gradually, never by a jump.

Every point is named by its taught keypoint's index (its id, stable from frame to frame).
"""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Optional

import cv2
import msgspec
import numpy as np

from protocol.messages import MAX_FEATURE_POINTS, FeatureStatus, FrontEnd, KeypointView, Pose
from services.model import frames
from services.runtime.config import ConfigStruct
from services.vision import features as F
from services.vision.front_end import Camera, Goal, Seen
from services.vision.taught import EQUALIZATIONS, TaughtGoal


class KeypointConfig(ConfigStruct):
    """The keypoint front end's settings (each number's source, or why it is ours)."""

    #: the detector a teach uses (a taught goal keeps its own): sift (default: accurate, 40-130 ms a 640×480 frame
    #: on one core here) or orb (the fast option, about a tenth of that); both in opencv-python-headless
    detector: str = "sift"
    #: the contrast equalization a teach's images get before the detector (a taught goal keeps its own: EQUALIZATIONS)
    equalization: str = "clahe"
    #: Lowe's ratio test: a match is kept when its distance is under this fraction of the second nearest's (Lowe,
    #: IJCV 2004; CNS's front end uses 0.75)
    ratio: float = 0.75
    #: MAGSAC's inlier threshold (px): a transfer (homography) or Sampson (epipolar) error under it is an inlier
    model_threshold_px: float = 3.0
    #: the fewest inliers to trust a pose (our choice: twice the six a pose has, so that one bad point cannot carry
    #: it alone)
    min_inliers: int = 12
    #: a point whose reprojection error under the pose is over this is dropped (px; the object seen k times farther
    #: than taught: k times this, its keypoints found again at coarser scales)
    max_error_px: float = 2.0
    #: ... and the target is lost when the inliers' median error is over this (px, scaled the same): the view is not
    #: the taught object's, or the object's 3D points do not fit it
    max_median_error_px: float = 1.0
    #: detect every this many frames, tracking in between (1: detect on every frame); also when fewer than
    #: ``min_tracked`` points survive the tracking
    detect_every: int = 5
    min_tracked: int = 30
    #: the detection window: the object's last outline grown by this fraction of its size on every side (the object
    #: moves between frames), or the whole image
    window_margin: float = 0.3
    #: pyramidal LK (OpenCV's defaults but for the window): window (px), pyramid levels, and the forward-backward
    #: check's bound (px)
    lk_window_px: int = 21
    lk_levels: int = 3
    lk_back_px: float = 0.5
    #: how many frames a point takes to fade in or out (a sixth of a second at 30 Hz)
    fade_frames: int = 5
    #: the smallest spread the robust weights take (px): below it every inlier counts in full (a rendered view the
    #: pose explains to a few hundredths of a pixel has nothing to weigh down)
    robust_floor_px: float = 0.1
    #: the most points handed to the controller (the message carries 512): the taught keypoints' strongest
    max_points: int = 200
    #: the detector's keypoints per image (0: all it finds)
    max_image_features: int = 0

    def __post_init__(self) -> None:
        if self.detector not in ("sift", "orb"):
            raise ValueError(f"keypoints.detector must be sift or orb, not {self.detector!r}")
        if self.equalization not in EQUALIZATIONS:
            raise ValueError(f"keypoints.equalization must be one of {', '.join(EQUALIZATIONS)}, not "
                             f"{self.equalization!r}")
        if not 0.3 <= self.ratio <= 0.95:
            raise ValueError("keypoints.ratio must be within 0.3..0.95")
        if not (4 <= self.min_inliers <= 500 and 1 <= self.detect_every <= 100 and 1 <= self.fade_frames <= 60):
            raise ValueError("keypoints need 4 <= min_inliers <= 500, 1 <= detect_every <= 100, 1 <= fade_frames <= 60")
        if not (0 < self.max_median_error_px <= self.max_error_px <= 20 and 0.5 <= self.model_threshold_px <= 20):
            raise ValueError("keypoints need 0 < max_median_error_px <= max_error_px <= 20 and a model threshold "
                             "within 0.5..20 px")
        if not 1 <= self.max_points <= MAX_FEATURE_POINTS:
            raise ValueError(f"keypoints.max_points must be within 1..{MAX_FEATURE_POINTS}")


#: SIFT's contrast threshold: OpenCV's default (its reading of Lowe's 0.03, IJCV 2004 section 4). Measured on the
#: simulator's cup from 0.65 m, the random starts' far end (2.25 times the taught distance) and turned 40°: 32
#: inliers, the bound 12; half of it (0.02) finds twice the matches but takes 2.5 times as long to detect
SIFT_CONTRAST_THRESHOLD = 0.04


#: the contrast equalization CLAHE (contrast-limited adaptive histogram equalization, Zuiderveld, Graphics Gems IV, 1994) as OpenCV's own tutorial sets it, a clip limit of 2 on
#: 8×8 tiles. Measured on the simulator's cup from the random starts' far end (0.5 m, 1.7 times the taught
#: distance) lit 50 % brighter from 30° elsewhere than taught: 9 to 30 of the taught keypoints matched on the frames
#: as rendered, under the 12 a pose needs on most; 43 to 106 equalized, and twice as many under the taught light
CLAHE_CLIP_LIMIT = 2.0
CLAHE_TILES = (8, 8)


def equalized(gray: np.ndarray, equalization: str) -> np.ndarray:
    """The image the detector sees (the tracking follows the frames as they are): a light changed between the teach
    and the servo changes a curved object's shading across it, and SIFT's and ORB's descriptors, normalised for a
    patch's contrast only, follow the shading."""
    if equalization == "none":
        return gray
    if equalization != "clahe":
        raise ValueError(f"unknown equalization {equalization!r}: one of {', '.join(EQUALIZATIONS)}")
    return cv2.createCLAHE(clipLimit=CLAHE_CLIP_LIMIT, tileGridSize=CLAHE_TILES).apply(gray)


def make_detector(kind: str, max_features: int = 0):
    """OpenCV's SIFT or ORB (one thread: the services share two cores)."""
    if kind == "sift":
        return cv2.SIFT_create(nfeatures=max_features, contrastThreshold=SIFT_CONTRAST_THRESHOLD)
    return cv2.ORB_create(nfeatures=max_features or 3000, scaleFactor=1.2, nlevels=8, fastThreshold=10)


def matcher_for(kind: str):
    """A brute-force matcher for the descriptors (deterministic: FLANN's randomised trees are not)."""
    return cv2.BFMatcher(cv2.NORM_L2 if kind == "sift" else cv2.NORM_HAMMING, crossCheck=False)


def ratio_matches(taught: np.ndarray, found: np.ndarray, matcher, ratio: float) -> list[tuple[int, int, float]]:
    """(taught index, found index, distance) of each taught descriptor whose nearest found one passes the ratio
    test, each found keypoint used once (the closer match keeps it)."""
    if len(found) < 2 or len(taught) == 0:
        return []
    best: dict[int, tuple[int, int, float]] = {}
    for pair in matcher.knnMatch(taught, found, k=2):
        if len(pair) < 2:
            continue
        first, second = pair
        if first.distance < ratio * second.distance:
            kept = best.get(first.trainIdx)
            if kept is None or first.distance < kept[2]:
                best[first.trainIdx] = (first.queryIdx, first.trainIdx, first.distance)
    return sorted(best.values())


def homography_inliers(taught_px: np.ndarray, found_px: np.ndarray, threshold_px: float
                       ) -> tuple[Optional[np.ndarray], np.ndarray]:
    """(H, inlier mask) by MAGSAC, the inliers counted again from our own transfer errors ‖H·x − x'‖."""
    if len(taught_px) < 4:
        return None, np.zeros(len(taught_px), bool)
    try:
        H, _ = cv2.findHomography(taught_px.reshape(-1, 1, 2), found_px.reshape(-1, 1, 2), cv2.USAC_MAGSAC,
                                  threshold_px, maxIters=5000, confidence=0.999)
    except cv2.error:  # USAC asserts on some degenerate samples (all points on a line): no homography
        return None, np.zeros(len(taught_px), bool)
    if H is None or not np.all(np.isfinite(H)):
        return None, np.zeros(len(taught_px), bool)
    moved = cv2.perspectiveTransform(taught_px.reshape(-1, 1, 2), H).reshape(-1, 2)
    return H, np.linalg.norm(moved - found_px, axis=1) < threshold_px


def homography_problem(H: np.ndarray, region_px: np.ndarray, width: int, height: int) -> str:
    """Why a homography cannot be the taught object's (mirrored, folded, degenerate, collapsed or blown up), or
    ""."""
    outline = cv2.perspectiveTransform(region_px.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    # the outline's points must all be in front of the homography's line at infinity, and the region keep its turn
    w = (np.column_stack([region_px, np.ones(len(region_px))]) @ H.T)[:, 2]
    if np.any(w <= 0):
        return "degenerate view: the homography folds the taught region"
    taught_area = _signed_area(region_px)
    area = _signed_area(outline)
    if taught_area * area <= 0:
        return "mirrored view: the homography turns the taught region over"
    ratio = abs(area / taught_area)
    if not 1e-3 <= ratio <= 1e3:
        return f"degenerate view: the region's area changes {ratio:.3g}-fold"
    if not cv2.isContourConvex(outline.astype(np.float32)) and cv2.isContourConvex(region_px.astype(np.float32)):
        return "degenerate view: the convex taught region seen as a concave one"
    return ""


def _signed_area(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def epipolar_inliers(taught_px: np.ndarray, found_px: np.ndarray, threshold_px: float) -> Optional[np.ndarray]:
    """The inlier mask of the epipolar constraint by MAGSAC (a fundamental matrix), counted again from our own Sampson
    distances; None when there is no fundamental matrix to have (too few points, or a degenerate set: nearly
    planar, or nearly no motion, where the epipolar geometry is undefined and OpenCV's USAC asserts)."""
    if len(taught_px) < 8:
        return None
    try:
        Fm, _ = cv2.findFundamentalMat(taught_px, found_px, cv2.USAC_MAGSAC, threshold_px, 0.999, 5000)
    except cv2.error:
        return None
    if Fm is None or Fm.shape != (3, 3) or not np.all(np.isfinite(Fm)):
        return None
    x1 = np.column_stack([taught_px, np.ones(len(taught_px))])
    x2 = np.column_stack([found_px, np.ones(len(found_px))])
    Fx1, Ftx2 = x1 @ Fm.T, x2 @ Fm
    num = np.sum(x2 * Fx1, axis=1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12)) < threshold_px


def object_pose(points_3d: np.ndarray, pixels: np.ndarray, camera: Camera,
                guess: Optional[tuple[np.ndarray, np.ndarray]] = None,
                robust_px: Optional[float] = None) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """(rvec, tvec) of the taught camera frame in this camera's (the object's 3D points, as taught, seen at
    ``pixels``): the last pose refined (``guess``), RANSAC over EPnP with this inlier bound (``robust_px``: the
    epipolar constraint lets a match slide along its epipolar line, so a non-planar object's candidates still hold
    outliers), or SQPnP; then Levenberg-Marquardt; None if there is none."""
    dist = camera.distortion if np.any(camera.distortion) else None
    obj = np.ascontiguousarray(points_3d, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    if robust_px is not None and guess is None:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(obj, img, camera.K, dist, reprojectionError=robust_px,
                                                     iterationsCount=500, confidence=0.999,
                                                     flags=cv2.SOLVEPNP_EPNP)
        if not ok or inliers is None or len(inliers) < 4:
            return None
        keep = inliers.ravel()
        obj, img = obj[keep], img[keep]
    elif guess is not None:
        rvec, tvec = guess[0].copy(), guess[1].copy()
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, dist, rvec, tvec, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, dist, rvec, tvec)
    return rvec.reshape(3), tvec.reshape(3)


def project(points_3d: np.ndarray, pose: tuple[np.ndarray, np.ndarray], camera: Camera) -> np.ndarray:
    dist = camera.distortion if np.any(camera.distortion) else None
    pixels, _ = cv2.projectPoints(np.ascontiguousarray(points_3d, dtype=np.float64).reshape(-1, 1, 3), pose[0],
                                  pose[1], camera.K, dist)
    return pixels.reshape(-1, 2)


#: Tukey's biweight constant: 95 % efficiency at the normal distribution (Holland and Welsch, 1977; ViSP's vpRobust)
TUKEY_C = 4.6851
#: the median absolute deviation's factor to the normal's standard deviation
MAD_TO_SIGMA = 1.4826


def tukey_weights(residuals: np.ndarray, floor: float) -> np.ndarray:
    """Tukey's biweight of each residual over the robust spread σ = max(1.4826 · median |r|, ``floor``):
    (1 − (r / cσ)²)² within cσ, 0 beyond."""
    r = np.abs(np.asarray(residuals, dtype=float))
    sigma = max(MAD_TO_SIGMA * float(np.median(r)), floor) if len(r) else floor
    u = r / (TUKEY_C * sigma)
    return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)


@dataclass
class _Tracked:
    """The points handed over last frame, by id: pixel, weight, and whether they were measured (not predicted)."""

    pixels: dict[int, np.ndarray] = field(default_factory=dict)
    #: each point's fade (0..1)
    weights: dict[int, float] = field(default_factory=dict)
    measured: dict[int, bool] = field(default_factory=dict)
    #: each point's robust weight when it was last measured
    robust: dict[int, float] = field(default_factory=dict)


class KeypointFrontEnd:
    """Finds a taught goal's keypoints in each image (module doc). A pure core: the same frames give the same
    points."""

    kind = FrontEnd.KEYPOINTS

    def __init__(self, taught: TaughtGoal, config: KeypointConfig, min_peak_brightness: int = 0,
                 border_margin_px: float = 2.0, background: bool = False) -> None:
        """``background``: detect on a thread of its own while the frames are tracked (realtime: a SIFT detection
        takes longer than a camera period, and each frame's points must not wait for it; the detection's points are
        then carried to the frame at hand by LK and checked there). Lockstep detects in the frame's own turn, so
        that a run is a function of its frames."""
        self.taught = taught
        self.config = config
        self.detector_kind = taught.file.detector
        self.equalization = taught.file.equalization
        self.detector = make_detector(self.detector_kind, config.max_image_features)
        self.matcher = matcher_for(self.detector_kind)
        self.planar = taught.file.planar
        self.min_peak_brightness = min_peak_brightness
        self.border_margin_px = border_margin_px
        self.region = taught.region()
        #: the taught keypoints handed over at most: the ones nearest the region's centre first would bias the
        #: pose; the taught order is the detector's (its strongest first), kept
        self._usable = np.arange(len(taught.keypoints_px))
        self._last_gray: Optional[np.ndarray] = None
        self._pose: Optional[tuple[np.ndarray, np.ndarray]] = None
        self._tracked = _Tracked()
        self._since_detect = 0
        self._background: Optional[ThreadPoolExecutor] = None
        #: the detection running in the background: its future and the frame it runs on
        self._pending: Optional[tuple[Future, np.ndarray]] = None
        if background:
            self._background = ThreadPoolExecutor(1, thread_name_prefix="keypoints-detect")
            self._background_detector = make_detector(self.detector_kind, config.max_image_features)

    def close(self) -> None:
        if self._background is not None:
            self._background.shutdown(wait=False, cancel_futures=True)

    # ------------------------------------------------------------------ one image
    def measure(self, gray: np.ndarray, camera: Camera, goal: Goal) -> Seen:
        started = time.perf_counter()
        seen = self._measure(gray, camera, goal)
        if seen.view is not None:
            seen.view = msgspec.structs.replace(seen.view, took_ms=1e3 * (time.perf_counter() - started))
        return seen

    def _measure(self, gray: np.ndarray, camera: Camera, goal: Goal) -> Seen:
        cfg = self.config
        if int(gray.max()) < self.min_peak_brightness:
            self._forget()
            return Seen(FeatureStatus.INVALID_IMAGE, "all-black image", rejected=True)
        if self._background is not None and self._tracked.pixels and self._last_gray is not None:
            seen = self._measure_alongside(gray, camera, goal)
            if seen is not None:
                return seen
        search = "track"
        ids = pixels = None
        candidates = 0
        if self._tracked.pixels and self._last_gray is not None and self._since_detect + 1 < cfg.detect_every:
            ids, pixels = self._track(gray)
            candidates = len(ids)
            self._since_detect += 1
            if len(ids) < cfg.min_tracked:
                ids = None
        if ids is None:
            search = "detect"
            ids, pixels, reason = self._detect(gray, camera)
            candidates = len(ids)
            self._since_detect = 0
            if reason:
                return self._lost(reason, gray, search, candidates)
        result = self._verify(ids, pixels, camera, search)
        if isinstance(result, str):
            return self._lost(result, gray, search, candidates)
        ids, pixels, pose, errors = result
        return self._hand_over(ids, pixels, pose, errors, gray, camera, goal, search, candidates)

    def _measure_alongside(self, gray: np.ndarray, camera: Camera, goal: Goal) -> Optional[Seen]:
        """A frame while the detections run in the background: the finished detection's points carried to this
        frame (LK from the frame it ran on) and checked, else this frame tracked; a detection started when one is
        due. None when too few points are left to track (the caller detects in this frame's turn)."""
        cfg = self.config
        if self._pending is not None and self._pending[0].done():
            future, then = self._pending
            self._pending = None
            ids, pixels, reason = future.result()
            if not reason and len(ids) >= cfg.min_inliers:
                ids, pixels = self._follow(then, gray, ids, pixels)
                result = self._verify(ids, pixels, camera, "detect")
                if not isinstance(result, str):
                    return self._hand_over(*result, gray, camera, goal, "detect", len(ids))
        ids, pixels = self._track(gray)
        self._since_detect += 1
        if self._pending is None and self._since_detect + 1 >= cfg.detect_every:
            window = self._window(camera)
            self._pending = (self._background.submit(self._detect, gray.copy(), camera, window,
                                                     self._background_detector), gray.copy())
            self._since_detect = 0
        if len(ids) < cfg.min_tracked:
            return None
        result = self._verify(ids, pixels, camera, "track")
        if isinstance(result, str):
            return self._lost(result, gray, "track", len(ids))
        return self._hand_over(*result, gray, camera, goal, "track", len(ids))

    def _follow(self, then: np.ndarray, now: np.ndarray, ids: np.ndarray, pixels: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """Points found in frame ``then`` carried to frame ``now`` (pyramidal LK, forward and back)."""
        cfg = self.config
        before = pixels.astype(np.float32).reshape(-1, 1, 2)
        params = dict(winSize=(cfg.lk_window_px, cfg.lk_window_px), maxLevel=cfg.lk_levels,
                      criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        after, status, _ = cv2.calcOpticalFlowPyrLK(then, now, before, None, **params)
        back, back_status, _ = cv2.calcOpticalFlowPyrLK(now, then, after, None, **params)
        keep = ((status.ravel() == 1) & (back_status.ravel() == 1)
                & (np.linalg.norm((back - before).reshape(-1, 2), axis=1) < cfg.lk_back_px))
        return ids[keep], after.reshape(-1, 2).astype(float)[keep]

    def _forget(self) -> None:
        self._last_gray, self._pose, self._tracked = None, None, _Tracked()

    def _lost(self, reason: str, gray: np.ndarray, search: str, candidates: int) -> Seen:
        self._forget()
        self._last_gray = gray
        counted = reason.split(":", 1)[0].replace(" ", "_")
        return Seen(FeatureStatus.TARGET_LOST, reason, counts=[f"keypoints.{search}", f"lost.{counted}"],
                    view=self._view(search, candidates, 0, None, None, None))

    # ------------------------------------------------------------------ finding the points
    def _window(self, camera: Camera) -> Optional[tuple[int, int, int, int]]:
        if self._pose is None:
            return None
        outline = project(self._outline_3d(), self._pose, camera)
        lo, hi = outline.min(axis=0), outline.max(axis=0)
        margin = self.config.window_margin * (hi - lo) + 16.0
        x0, y0 = np.floor(np.maximum(lo - margin, 0)).astype(int)
        x1, y1 = np.ceil(np.minimum(hi + margin, (camera.width, camera.height))).astype(int)
        if x1 - x0 < 32 or y1 - y0 < 32:
            return None
        return int(x0), int(y0), int(x1), int(y1)

    def _detect(self, gray: np.ndarray, camera: Camera, window=False, detector=None
                ) -> tuple[np.ndarray, np.ndarray, str]:
        """The taught keypoints matched in ``gray`` (in ``window``, by default around the object's last outline):
        (taught ids, pixels, "") or why too few."""
        window = self._window(camera) if window is False else window
        x0, y0 = (0, 0) if window is None else window[:2]
        image = equalized(gray, self.equalization)  # the whole frame's tiles, wherever the window is
        image = image if window is None else image[y0:window[3], x0:window[2]]
        keypoints, descriptors = (detector or self.detector).detectAndCompute(image, None)
        if descriptors is None or len(keypoints) < self.config.min_inliers:
            found = 0 if descriptors is None else len(keypoints)
            return np.zeros(0, int), np.zeros((0, 2)), f"too few keypoints: {found} in the image"
        matches = ratio_matches(self.taught.descriptors, descriptors, self.matcher, self.config.ratio)
        if len(matches) < self.config.min_inliers:
            return np.zeros(0, int), np.zeros((0, 2)), (f"too few matches: {len(matches)} of the taught keypoints "
                                                        f"(at least {self.config.min_inliers})")
        ids = np.array([m[0] for m in matches], dtype=int)
        pixels = np.array([keypoints[m[1]].pt for m in matches], dtype=float) + np.array([x0, y0], dtype=float)
        return ids, pixels, ""

    def _track(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The last frame's measured points followed into this one (pyramidal LK, forward and back)."""
        cfg = self.config
        ids = np.array([i for i in self._tracked.pixels if self._tracked.measured[i]], dtype=int)
        if len(ids) == 0:
            return ids, np.zeros((0, 2))
        before = np.array([self._tracked.pixels[i] for i in ids], dtype=np.float32).reshape(-1, 1, 2)
        params = dict(winSize=(cfg.lk_window_px, cfg.lk_window_px), maxLevel=cfg.lk_levels,
                      criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        after, status, _ = cv2.calcOpticalFlowPyrLK(self._last_gray, gray, before, None, **params)
        back, back_status, _ = cv2.calcOpticalFlowPyrLK(gray, self._last_gray, after, None, **params)
        good = ((status.ravel() == 1) & (back_status.ravel() == 1)
                & (np.linalg.norm((back - before).reshape(-1, 2), axis=1) < cfg.lk_back_px))
        height, width = gray.shape[:2]
        after = after.reshape(-1, 2).astype(float)
        inside = (after[:, 0] >= 0) & (after[:, 1] >= 0) & (after[:, 0] <= width - 1) & (after[:, 1] <= height - 1)
        keep = good & inside
        return ids[keep], after[keep]

    # ------------------------------------------------------------------ checking them
    def _verify(self, ids: np.ndarray, pixels: np.ndarray, camera: Camera, search: str):
        """(ids, pixels, pose, reprojection errors) of the inliers, or why the target is lost."""
        cfg = self.config
        taught_px = self.taught.keypoints_px[ids]
        if self.planar:
            H, mask = homography_inliers(taught_px, pixels, cfg.model_threshold_px)
            if H is None or mask.sum() < cfg.min_inliers:
                return f"too few inliers: {int(mask.sum())} fit one homography (at least {cfg.min_inliers})"
            problem = homography_problem(H, self.region, camera.width, camera.height)
            if problem:
                return problem
        else:
            mask = epipolar_inliers(taught_px, pixels, cfg.model_threshold_px)
            if mask is None:  # no epipolar geometry to check against: PnP's RANSAC alone rejects the outliers
                mask = np.ones(len(ids), bool)
            if mask.sum() < cfg.min_inliers:
                return f"too few inliers: {int(mask.sum())} fit the epipolar constraint (at least {cfg.min_inliers})"
        ids, pixels = ids[mask], pixels[mask]
        points = self.taught.points_camera[ids]
        pose = object_pose(points, pixels, camera, self._pose if search == "track" else None,
                           robust_px=cfg.model_threshold_px)
        if pose is None:
            return "no pose: PnP found none for the inliers"
        scale = self._farther(points, pose)
        bound, median_bound = cfg.max_error_px * scale, cfg.max_median_error_px * scale
        for _ in range(2):  # drop the points the pose does not explain, and fit again on the rest
            errors = np.linalg.norm(project(points, pose, camera) - pixels, axis=1)
            keep = errors <= bound
            if keep.sum() < cfg.min_inliers:
                return (f"too few inliers: {int(keep.sum())} within {bound:.2g} px of the pose "
                        f"(at least {cfg.min_inliers})")
            if keep.all():
                break
            ids, pixels, points = ids[keep], pixels[keep], points[keep]
            pose = object_pose(points, pixels, camera, pose)
            if pose is None:
                return "no pose: PnP found none for the inliers"
        errors = np.linalg.norm(project(points, pose, camera) - pixels, axis=1)
        median = float(np.median(errors))
        if median > median_bound:
            return (f"reprojection error {median:.2f} px over the bound {median_bound:.2g} px "
                    "(not the taught object, or not its shape)")
        R, _ = cv2.Rodrigues(pose[0])
        if np.any((points @ R.T + pose[1])[:, 2] <= 0):
            return "implausible pose: a point behind the camera"
        return ids, pixels, pose, errors

    def _farther(self, points: np.ndarray, pose) -> float:
        """How many times farther than taught the object is (at least 1): a keypoint found again at a coarser scale
        sits up to a pixel or two from where its taught one projects (measured: a median of 1.0-1.2 px at 1.7 to 1.9
        times the taught distance, on the simulator's objects), so the reprojection bounds grow with it."""
        R, _ = cv2.Rodrigues(pose[0])
        now = float(np.median((points @ R.T + pose[1])[:, 2]))
        return max(1.0, now / float(np.median(points[:, 2])))

    # ------------------------------------------------------------------ handing them over
    def _hand_over(self, ids, pixels, pose, errors, gray, camera: Camera, goal: Goal, search: str,
                   candidates: int) -> Seen:
        cfg = self.config
        step = 1.0 / cfg.fade_frames
        was = self._tracked
        continuing = bool(was.pixels)
        measured = {int(i): p for i, p in zip(ids, pixels)}
        robust = dict(zip((int(i) for i in ids), tukey_weights(errors, cfg.robust_floor_px)))
        weights: dict[int, float] = {}
        for i in measured:
            weights[i] = min(1.0, was.weights.get(i, 0.0) + step) if continuing else 1.0
        # the strongest (lowest taught index) first, up to the message's share
        order = sorted(measured)[: cfg.max_points]
        chosen = set(order)
        leaving = [i for i in was.pixels if i not in chosen and was.weights[i] - step > 1e-9]
        all_pixels = dict((i, measured[i]) for i in order)
        if leaving:
            predicted = project(self.taught.points_camera[leaving], pose, camera)
            for i, p in zip(leaving, predicted):
                all_pixels[i] = p
                weights[i] = was.weights[i] - step
        final_ids = np.array(sorted(all_pixels), dtype=int)
        final_px = np.array([all_pixels[i] for i in final_ids], dtype=float)
        final_w = np.array([weights[i] for i in final_ids], dtype=float)  # each point's fade
        handed = final_w * np.array([robust.get(int(i), was.robust.get(int(i), 1.0)) for i in final_ids])
        if not np.any(handed > 0.0):
            handed = final_w
        R, _ = cv2.Rodrigues(pose[0])
        in_camera = self.taught.points_camera[final_ids] @ R.T + pose[1]
        normalized = F.normalize(final_px, camera.K, camera.distortion)
        self._tracked = _Tracked({int(i): p for i, p in zip(final_ids, final_px)},
                                 {int(i): float(w) for i, w in zip(final_ids, final_w)},
                                 {int(i): int(i) in measured and int(i) in chosen for i in final_ids},
                                 {int(i): robust.get(int(i), was.robust.get(int(i), 1.0)) for i in final_ids})
        self._pose, self._last_gray = pose, gray
        outline = project(self._outline_3d(), pose, camera)
        partial = F.touches_border(outline, camera.width, camera.height, self.border_margin_px)
        seen = Seen(FeatureStatus.PARTIAL if partial else FeatureStatus.OK,
                    "the object's region crosses the image border" if partial else "",
                    points=normalized, depths=in_camera[:, 2], ids=final_ids, weights=handed, pixels=final_px,
                    counts=[f"keypoints.{search}"])
        inlier_errors = errors[np.isin(ids, final_ids)]
        seen.view = self._view(search, candidates, len(ids), inlier_errors, pose, outline)
        return seen

    def _outline_3d(self) -> np.ndarray:
        """The taught region's outline in 3D (the taught camera's frame): on the object's plane for a planar goal,
        else at the depth of the nearest keypoints' median (a cup's outline is only drawn, never measured)."""
        f = self.taught.file
        K_inv = np.linalg.inv(self.taught.camera_matrix)
        rays = np.column_stack([self.region, np.ones(len(self.region))]) @ K_inv.T
        if f.planar:
            n, d = np.asarray(f.plane_normal), float(f.plane_distance_m)
            scale = d / np.maximum(-(rays @ n), 1e-9)
            return rays * scale[:, None]
        return rays * float(np.median(self.taught.points_camera[:, 2]))

    def _view(self, search: str, candidates: int, inliers: int, errors, pose, outline) -> KeypointView:
        pose_message = None
        if pose is not None:
            R, _ = cv2.Rodrigues(pose[0])
            pose_message = Pose(xyz=tuple(float(v) for v in pose[1]), quat_wxyz=tuple(frames.matrix_to_quat_wxyz(R)))
        return KeypointView(
            goal=self.taught.name, goal_digest=self.taught.digest, detector=self.detector_kind, search=search,
            candidates=candidates, inliers=inliers,
            median_error_px=float(np.median(errors)) if errors is not None and len(errors) else 0.0,
            max_error_px=float(np.max(errors)) if errors is not None and len(errors) else 0.0,
            model="homography" if self.planar else "epipolar", object_pose_in_camera=pose_message,
            region_px=[] if outline is None else [(float(x), float(y)) for x, y in outline[:64]])


def taught_goal_points(taught: TaughtGoal) -> Goal:
    """The servo's goal of a taught view: each keypoint where it was taught (normalized), at its taught depth, by
    its index."""
    return Goal(taught.normalized(), taught.points_camera[:, 2], f"taught {taught.name} ({taught.digest})",
                ids=np.arange(len(taught.points_camera)))


