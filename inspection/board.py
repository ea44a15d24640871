"""The ChArUco calibration board: its layout, OpenCV object and printed image.

Board frame (OpenCV's): origin at the outer corner of the first chessboard
square, x along the columns, y along the rows (down the printed image), z into
the board (away from the printed face). Units are millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from .arrays import Transform
from .errors import InvalidInput


@dataclass(frozen=True)
class CharucoSpec:
    """Layout of a ChArUco board.

    The default is a 12 x 9 board of 40 mm squares (480 x 360 mm plus a 12 mm
    white rim): large enough to span a third of the measurement volume, with
    markers of ~37 pixels in the rig's images (~5 pixels per marker bit),
    which OpenCV detects reliably at the tilts calibration needs.

    Attributes
    ----------
    squares_x, squares_y : int
        Chessboard squares along x and y.
    square_mm : float
        Side of a chessboard square.
    marker_mm : float
        Side of an ArUco marker (< square_mm).
    dictionary : str
        Name of the predefined ArUco dictionary in ``cv2.aruco``.
    rim_mm : float
        White rim around the squares on the physical board.
    """

    squares_x: int = 12
    squares_y: int = 9
    square_mm: float = 40.0
    marker_mm: float = 30.0
    dictionary: str = "DICT_5X5_100"
    rim_mm: float = 12.0

    def __post_init__(self) -> None:
        if self.squares_x < 3 or self.squares_y < 3:
            raise InvalidInput("a ChArUco board needs at least 3 x 3 squares")
        if not 0 < self.marker_mm < self.square_mm:
            raise InvalidInput("marker_mm must be positive and smaller than square_mm")
        if self.rim_mm < 0:
            raise InvalidInput("rim_mm must be >= 0")
        if not hasattr(cv2.aruco, self.dictionary):
            raise InvalidInput(f"unknown ArUco dictionary {self.dictionary!r}")

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the chessboard area, mm."""
        return (self.squares_x * self.square_mm, self.squares_y * self.square_mm)

    @property
    def centre_mm(self) -> npt.NDArray[np.float64]:
        """(3,) float64: the centre of the chessboard area in the board frame."""
        w, h = self.size_mm
        return np.array([w / 2.0, h / 2.0, 0.0])

    def make_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (object points in mm)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_mm, self.marker_mm, dictionary
        )

    def corners_mm(self) -> npt.NDArray[np.float64]:
        """(N, 3) float64: the inner chessboard corners in the board frame, by ChArUco id."""
        return np.asarray(self.make_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def texture(self, px_per_mm: float = 8.0) -> npt.NDArray[np.uint8]:
        """The printed chessboard area as an image.

        Returns
        -------
        (squares_y * square_mm * px_per_mm, squares_x * square_mm * px_per_mm) uint8
            Texel (col, row) covers board coordinates [col, col + 1) / px_per_mm
            along x and [row, row + 1) / px_per_mm along y.
        """
        sq = self.square_mm * px_per_mm
        if abs(sq - round(sq)) > 1e-9:
            raise InvalidInput("square_mm * px_per_mm must be a whole number of pixels")
        size = (self.squares_x * int(round(sq)), self.squares_y * int(round(sq)))
        image = self.make_board().generateImage(size, marginSize=0, borderBits=1)
        return np.asarray(image, dtype=np.uint8)


def board_lying_flat(
    spec: CharucoSpec,
    centre_xy_mm: tuple[float, float] = (0.0, 0.0),
    yaw_deg: float = 0.0,
    height_mm: float = 0.0,
) -> Transform:
    """T_rig_board of a board lying face up on the belt.

    Parameters
    ----------
    spec : CharucoSpec
    centre_xy_mm : (float, float)
        Where the centre of the chessboard area lies in the rig frame.
    yaw_deg : float
        Rotation about rig z; at 0 the board's x axis runs along rig +x (and,
        the printed face looking up, its y axis along rig -y).
    height_mm : float
        Height of the printed face above the belt (the board's thickness).

    Returns
    -------
    (4, 4) float64
        Maps board-frame points into the rig frame.
    """
    a = np.deg2rad(yaw_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    R = Rz @ np.diag([1.0, -1.0, -1.0])  # face up: board z (into the board) points down
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([centre_xy_mm[0], centre_xy_mm[1], height_mm]) - R @ spec.centre_mm
    return T
