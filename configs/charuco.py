"""The ChArUco calibration board, defined once: the twin (sim/) textures it, the hand-eye solver
(planners/) detects it, and neither may import the other.

Board frame (OpenCV's): origin at the outer corner of the top-left square of the printed image, x
along the image columns, y along the image rows, z into the board (away from a viewer of the
printed face). Chessboard corner ``i`` of OpenCV's ``getChessboardCorners()`` lies at
((i % (squares_x - 1)) + 1, (i // (squares_x - 1)) + 1) * square_m.
"""

from __future__ import annotations

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator


class CharucoBoardConfig(BaseModel):
    """A printed ChArUco board. The default, 7 x 5 squares of 40 mm with 30 mm DICT_5X5_100 markers
    (280 x 200 mm plus a 20 mm white margin: 320 x 240 mm), is printed on A3 at 100 % scale."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    squares_x: int = Field(7, ge=3, le=30)
    squares_y: int = Field(5, ge=3, le=30)
    square_m: float = Field(0.040, gt=0.005, le=0.5)
    marker_m: float = Field(0.030, gt=0.003, le=0.5)
    dictionary: str = "DICT_5X5_100"
    margin_m: float = Field(0.020, ge=0.0, le=0.2, description="white border around the squares (the outer "
                            "markers need some quiet zone to be found)")

    @field_validator("dictionary")
    @classmethod
    def _known_dictionary(cls, v: str) -> str:
        if not v.startswith("DICT_") or not isinstance(getattr(cv2.aruco, v, None), int):
            raise ValueError(f"{v!r} is not an OpenCV ArUco dictionary (e.g. DICT_5X5_100)")
        return v

    @model_validator(mode="after")
    def _fits(self) -> "CharucoBoardConfig":
        if self.marker_m >= self.square_m:
            raise ValueError(f"marker_m {self.marker_m} must be smaller than square_m {self.square_m}")
        n_markers = (self.squares_x * self.squares_y) // 2
        size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]
        if n_markers > size:
            raise ValueError(f"{self.squares_x} x {self.squares_y} squares need {n_markers} markers; "
                             f"{self.dictionary} has {size}")
        return self

    def board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (a new one each call: OpenCV objects are not shared across threads)."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the squares (margin not included)."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    @property
    def corners_m(self) -> np.ndarray:
        """(N, 3) chessboard corners in the board frame, in OpenCV's id order."""
        return np.asarray(self.board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def image(self, px_per_square: int = 100) -> np.ndarray:
        """The printable image, uint8 grey (H, W), margin included: exactly ``px_per_square`` pixels
        per square, so pixel (column c, row r) covers board x in [c, c+1) * square_m / px_per_square
        - margin_m (same for y with rows)."""
        margin_px = self.margin_px(px_per_square)
        w = self.squares_x * px_per_square + 2 * margin_px
        h = self.squares_y * px_per_square + 2 * margin_px
        return self.board().generateImage((w, h), marginSize=margin_px, borderBits=1)

    def margin_px(self, px_per_square: int) -> int:
        """The margin in whole image pixels (the printed margin is this times square_m / px_per_square)."""
        return int(round(self.margin_m / self.square_m * px_per_square))
