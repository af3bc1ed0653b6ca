"""AprilTag target geometry shared by the simulator (texture) and vision (detection, goal features).

Tag frame: OpenCV aruco's marker frame: origin at the tag centre, x right, y up, z out of the tag face.
``size_m`` is the edge of the black square (8 of the tag's cells for 36h11, border included).
Corner order is OpenCV's, as detected: top-left, top-right, bottom-right, bottom-left of the upright tag image,
i.e. (−s/2, +s/2), (+s/2, +s/2), (+s/2, −s/2), (−s/2, −s/2) in the tag frame.
"""
from __future__ import annotations

import numpy as np

FAMILIES = {"tag36h11": "DICT_APRILTAG_36h11"}
#: cells across the black square (6 data cells + 1 border cell each side) for tag36h11
BLACK_CELLS = 8
#: a white quiet zone of one cell around the black square, as printed tags have
QUIET_CELLS = 1


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


def tag_image(tag_id: int, family: str = "tag36h11", px_per_cell: int = 32) -> np.ndarray:
    """Upright grayscale image of the tag with its white quiet zone (uint8, square)."""
    import cv2

    marker = cv2.aruco.generateImageMarker(dictionary(family), int(tag_id), BLACK_CELLS * px_per_cell, borderBits=1)
    side = (BLACK_CELLS + 2 * QUIET_CELLS) * px_per_cell
    image = np.full((side, side), 255, np.uint8)
    q = QUIET_CELLS * px_per_cell
    image[q : q + marker.shape[0], q : q + marker.shape[1]] = marker
    return image
