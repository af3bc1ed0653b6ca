"""AprilTag target geometry shared by the simulator (texture) and vision (detection, goal features).

Tag frame: origin at the tag centre, x right, y up, z out of the tag face, of the upright tag image.
``size_m`` is the edge of the black square (8 of the tag's cells for 36h11, border included).
Corner order: top-left, top-right, bottom-right, bottom-left of the upright tag image, i.e. (−s/2, +s/2),
(+s/2, +s/2), (+s/2, −s/2), (−s/2, −s/2) in the tag frame.

Which image is upright is the tag's ``layout``. ``official``: the images of the AprilTag project
(github.com/AprilRobotics/apriltag-imgs, tag36h11/tag36_11_<id>.png), the ones to print. ``opencv``: OpenCV's
``generateImageMarker`` for DICT_APRILTAG_36h11, which draws the same codes turned (by 180° in OpenCV 4.x-5.0).
OpenCV detects either and orders the corners from its own image's top-left; for an official print that is a
turned corner, so the detector rotates the order back by the turn it measures, at start, between OpenCV's image
and the official one (``opencv_turns``), whatever OpenCV's version draws.
"""
from __future__ import annotations

import enum
import functools

import numpy as np

FAMILIES = {"tag36h11": "DICT_APRILTAG_36h11"}
#: cells across the black square (6 data cells + 1 border cell each side) for tag36h11
BLACK_CELLS = 8
#: a white quiet zone of one cell around the black square, as printed tags have
QUIET_CELLS = 1


class TagLayout(str, enum.Enum):
    """Which image of the tag is upright (what is printed)."""

    OFFICIAL = "official"
    OPENCV = "opencv"


#: the data cells (6×6, 1 white) of the official tag36h11 id 0, tag36_11_00000.png of AprilRobotics/apriltag-imgs:
#: the reference OpenCV's own drawing is compared with
OFFICIAL_DATA_ID0 = {"tag36h11": ("110101", "011101", "011000", "101000", "010110", "000100")}


def dictionary(family: str = "tag36h11"):
    import cv2

    if family not in FAMILIES:
        raise ValueError(f"unknown tag family {family!r}; known: {sorted(FAMILIES)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, FAMILIES[family]))


def corners_in_tag(size_m: float) -> np.ndarray:
    """4×3 corner coordinates in the tag frame, in detection order."""
    s = size_m / 2.0
    return np.array([[-s, s, 0.0], [s, s, 0.0], [s, -s, 0.0], [-s, -s, 0.0]])


def printed_edge(size_m: float) -> float:
    """Edge of the printed square including the white quiet zone."""
    return size_m * (BLACK_CELLS + 2 * QUIET_CELLS) / BLACK_CELLS


def _opencv_marker(tag_id: int, family: str, side_px: int) -> np.ndarray:
    import cv2

    return cv2.aruco.generateImageMarker(dictionary(family), int(tag_id), side_px, borderBits=1)


@functools.lru_cache(maxsize=None)
def opencv_turns(family: str = "tag36h11") -> int:
    """k such that the official image is OpenCV's turned k quarter turns counter-clockwise (np.rot90)."""
    cells = _opencv_marker(0, family, BLACK_CELLS)[1:-1, 1:-1] > 127
    official = np.array([[c == "1" for c in row] for row in OFFICIAL_DATA_ID0[family]])
    for k in range(4):
        if np.array_equal(np.rot90(cells, k), official):
            return k
    raise RuntimeError(f"OpenCV's {family} id 0 is not the official tag in any rotation: a different dictionary")


def official_order(corners_opencv: np.ndarray, family: str = "tag36h11") -> np.ndarray:
    """Corners as OpenCV orders them (from its own image's top-left) → in the official image's order. OpenCV's
    image turned k quarter turns counter-clockwise is the official one: each turn takes OpenCV's top-left corner
    one place back in the order (top-left → bottom-left), so official corner i is OpenCV's corner i + k."""
    return np.roll(np.asarray(corners_opencv), -opencv_turns(family), axis=0)


def opencv_order(corners_official: np.ndarray, family: str = "tag36h11") -> np.ndarray:
    """The inverse of :func:`official_order`: corners in the official image's order → in OpenCV's."""
    return np.roll(np.asarray(corners_official), opencv_turns(family), axis=0)


def tag_image(tag_id: int, family: str = "tag36h11", px_per_cell: int = 32,
              layout: TagLayout | str = TagLayout.OFFICIAL) -> np.ndarray:
    """Upright grayscale image of the tag with its white quiet zone (uint8, square), as ``layout`` draws it."""
    marker = _opencv_marker(tag_id, family, BLACK_CELLS * px_per_cell)
    if TagLayout(layout) is TagLayout.OFFICIAL:
        marker = np.ascontiguousarray(np.rot90(marker, opencv_turns(family)))
    side = (BLACK_CELLS + 2 * QUIET_CELLS) * px_per_cell
    image = np.full((side, side), 255, np.uint8)
    q = QUIET_CELLS * px_per_cell
    image[q : q + marker.shape[0], q : q + marker.shape[1]] = marker
    return image
