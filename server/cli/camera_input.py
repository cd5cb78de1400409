"""``steelscan map --frames``: the downward camera's images and ``camera.json``, checked
before any work, and turned into the map's camera factors
(:mod:`processing.mapping.camera_motion`)."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np

from server.cli.inputs import list_files
from server.errors import CommandError

log = logging.getLogger(__name__)

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
INTRINSICS = ("width", "height", "fx", "fy", "cx", "cy")


@dataclass(frozen=True)
class CameraInput:
    """The frames (file-name order), their times on the clouds' clock, and the camera."""

    files: list[Path]
    times: np.ndarray
    camera: dict[str, object]  # camera.json's intrinsics, T_tof_camera as a (4, 4) array


def _number(value: object, key: str, path: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise CommandError(f"{path}: {key} must be a finite number")
    return float(value)


def read_camera_input(folder: Path, cloud_times: np.ndarray) -> CameraInput:
    """The frames of ``folder`` and its ``camera.json`` (fields in the CLI contract),
    checked: intrinsics positive, ``T_tof_camera`` a rigid 4 x 4, ``timestamps`` one per
    image and increasing (else one image per cloud, at the clouds' ``cloud_times``)."""
    files = list_files(folder, IMAGE_EXTS, "image")
    path = folder / "camera.json"
    try:
        spec = json.loads(path.read_text())
    except FileNotFoundError:
        raise CommandError(f"{path}: missing (the camera's intrinsics and T_tof_camera)") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CommandError(f"{path}: {exc}") from None
    if not isinstance(spec, dict):
        raise CommandError(f"{path}: not a JSON object")
    missing = [k for k in (*INTRINSICS, "T_tof_camera") if k not in spec]
    if missing:
        raise CommandError(f"{path}: missing {', '.join(missing)}")
    camera: dict[str, object] = {k: _number(spec[k], k, path) for k in INTRINSICS}
    if min(float(camera[k]) for k in ("width", "height", "fx", "fy")) <= 0:  # type: ignore[arg-type]
        raise CommandError(f"{path}: width, height, fx and fy must be positive")
    try:
        T = np.asarray(spec["T_tof_camera"], dtype=np.float64)
    except (TypeError, ValueError):
        raise CommandError(f"{path}: T_tof_camera must be a 4x4 list of lists of numbers") from None
    if (
        T.shape != (4, 4)
        or not np.isfinite(T).all()
        or not np.allclose(T[3], (0, 0, 0, 1), atol=1e-6)
        or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-3)
        or np.linalg.det(T[:3, :3]) < 0
    ):
        raise CommandError(
            f"{path}: T_tof_camera must be a rigid transform (4x4, rotation and translation)"
        )
    camera["T_tof_camera"] = T
    if "timestamps" in spec:
        try:
            times = np.asarray(spec["timestamps"], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise CommandError(f"{path}: timestamps must be a list of numbers") from None
        if len(times) != len(files):
            raise CommandError(f"{path}: {len(times)} timestamps for {len(files)} images")
        if not np.isfinite(times).all() or (np.diff(times) <= 0).any():
            raise CommandError(f"{path}: timestamps must be finite and increasing")
    else:
        if len(files) != len(cloud_times):
            raise CommandError(
                f"{folder}: {len(files)} images for {len(cloud_times)} clouds; without "
                "timestamps in camera.json there is one image per cloud"
            )
        times = np.asarray(cloud_times, np.float64)
    return CameraInput(files, times, camera)


class Frames(Sequence[np.ndarray]):
    """The images as grey (H, W) uint8, read when asked for (a long session's frames need
    not fit in memory), each checked against camera.json's size."""

    def __init__(self, files: list[Path], width: int, height: int) -> None:
        self.files, self.width, self.height = files, width, height

    def __len__(self) -> int:
        return len(self.files)

    @overload
    def __getitem__(self, k: int) -> np.ndarray: ...
    @overload
    def __getitem__(self, k: slice) -> list[np.ndarray]: ...
    def __getitem__(self, k: int | slice) -> np.ndarray | list[np.ndarray]:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        import cv2

        path = self.files[k]
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise CommandError(f"{path}: not a readable image")
        if image.shape != (self.height, self.width):
            raise CommandError(
                f"{path}: {image.shape[1]}x{image.shape[0]} px, but camera.json says "
                f"{self.width}x{self.height}"
            )
        return image


def camera_factors(
    given: CameraInput, clouds: list[np.ndarray], cloud_times: np.ndarray
) -> tuple[object, dict[str, object]]:
    """The map's camera factors from the frames and the clouds, and what the report says of
    them."""
    from processing.mapping.camera_motion import CameraModel, camera_factors

    model = CameraModel.of(given.camera)
    width, height = model.width, model.height
    frames = Frames(given.files, width, height)
    factors, registered = camera_factors(frames, given.times, clouds, cloud_times, model)
    distances, steps = factors.distances_m, factors.steps
    if not np.isfinite(distances).any():
        log.warning("no cloud shows the surface under the camera: the map uses the ToF alone")
    report: dict[str, object] = {
        "frames": len(given.files),
        "frame_pairs_registered": registered,
        "frame_pairs": len(frames) - 1,
        "surface_distance_m": (
            round(float(np.nanmedian(distances)), 4) if np.isfinite(distances).any() else None
        ),
        "cloud_steps_linked": sum(s is not None for s in steps),
        # how unsure a step's length is: the scatter of the surface distances the clouds
        # measured (a plate on the plate, a surface the ToF did not see), relative
        "scale_error": round(float(factors.scale_sigma), 4),
    }
    log.info(
        "camera: %d of %d frame pairs registered, %d of %d cloud steps linked",
        registered,
        len(frames) - 1,
        report["cloud_steps_linked"],
        len(clouds) - 1,
    )
    return factors, report
