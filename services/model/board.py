"""The ChArUco calibration board: what is printed (OpenCV's own board, so OpenCV's detector finds it), its
geometry, and its detection. One description serves the calibration commands, the simulator (which can carry the
board as its target) and the tests.

The board's frame is OpenCV's: origin at a chessboard corner of the board's outer edge, x along the squares' rows,
y along the columns, z out of the board's back (the printed face looks along −z); ``getChessboardCorners`` gives the
inner corners in it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from services.runtime.config import ConfigStruct


class BoardConfig(ConfigStruct):
    """A ChArUco board as printed: squares across and down, the square's and the marker's edge (m), the markers'
    ArUco dictionary (OpenCV's name, e.g. DICT_5X5_100)."""

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.03
    marker_m: float = 0.022
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if not (3 <= self.squares_x <= 40 and 3 <= self.squares_y <= 40):
            raise ValueError("a board needs 3..40 squares each way")
        if not 0.0 < self.marker_m < self.square_m <= 0.5:
            raise ValueError("the marker must be smaller than the square (and the square at most 0.5 m)")
        if not self.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (OpenCV's names: DICT_5X5_100, ...)")

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_m, self.squares_y * self.square_m


def opencv_board(cfg: BoardConfig) -> "cv2.aruco.CharucoBoard":
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, cfg.dictionary))
    return cv2.aruco.CharucoBoard((cfg.squares_x, cfg.squares_y), cfg.square_m, cfg.marker_m, dictionary)


def board_image(cfg: BoardConfig, px_per_square: int = 120) -> np.ndarray:
    """The board's image as printed, edge to edge (grey uint8; a print adds its own white margin)."""
    size = (cfg.squares_x * px_per_square, cfg.squares_y * px_per_square)
    return opencv_board(cfg).generateImage(size, marginSize=0, borderBits=1)


def board_in_target(cfg: BoardConfig) -> np.ndarray:
    """The board's frame (OpenCV's) in the frame of the target that carries it (the simulator's: centred, the
    printed face at +z, its top edge toward +y)."""
    width, height = cfg.size_m
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = (-width / 2.0, height / 2.0, 0.0)
    return T


@dataclass
class BoardView:
    """The board's inner corners found in one image: their ids, where they are on the board (m) and in the image
    (px)."""

    ids: np.ndarray
    object_points: np.ndarray
    image_points: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


class BoardDetector:
    """Finds a board's inner corners (OpenCV's CharucoDetector, with its sub-pixel refinement)."""

    def __init__(self, cfg: BoardConfig) -> None:
        self.cfg = cfg
        self.board = opencv_board(cfg)
        self._detector = cv2.aruco.CharucoDetector(self.board)

    def find(self, gray: np.ndarray, min_corners: int = 6) -> Optional[BoardView]:
        """The corners seen, or None when fewer than ``min_corners`` (a pose or a calibration needs several)."""
        corners, ids, _, _ = self._detector.detectBoard(gray)
        if ids is None or len(ids) < min_corners:
            return None
        object_points, image_points = self.board.matchImagePoints(corners, ids)
        return BoardView(ids.reshape(-1), object_points.reshape(-1, 3).astype(np.float64),
                         image_points.reshape(-1, 2).astype(np.float64))
