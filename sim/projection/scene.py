"""C-arm scenes: Mitsuba scene files in ``scenes/`` plus the C-arm geometry they describe.

A scene file is an ordinary Mitsuba 3 XML scene (sensor + ``ctxreg_drr`` integrator) whose
``<default name="ctxreg_...">`` entries give the C-arm's geometry: source-to-detector distance
(``ctxreg_sdd_mm``), source-to-isocentre distance (``ctxreg_sod_mm``), detector rows and columns
and pixel spacing (mm), optionally the principal point (``ctxreg_cx``, ``ctxreg_cy`` in pixels).
ctxreg derives the Mitsuba sensor's field of view and principal-point offsets from them when it
loads the file at a chosen render size (a downsampled detector keeps the physical extent).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from sim.core.errors import InputError
from sim.projection.geometry import CArmGeometry
from sim.projection.backend import ensure_variant

DEFAULT_SCENE = "cios_fusion"


class SceneError(InputError):
    """A scene name or file cannot be used; the message names it and the problem."""


@dataclass(frozen=True)
class CArmScene:
    """A scene file and the full-resolution C-arm geometry it declares."""

    name: str
    path: Path
    description: str
    geometry: CArmGeometry

    def geometry_at(self, height: int | None = None, width: int | None = None) -> CArmGeometry:
        """The geometry for a render size (rows, cols); None keeps the detector's own size."""
        if height is None and width is None:
            return self.geometry
        h = self.geometry.height if height is None else int(height)
        w = self.geometry.width if width is None else int(width)
        if h < 1 or w < 1:
            raise SceneError(f"render size must be positive, got {h} x {w}")
        if abs(h / self.geometry.height - w / self.geometry.width) > 1e-9:
            raise SceneError(
                f"render size {h} x {w} does not keep the detector's aspect "
                f"{self.geometry.height} x {self.geometry.width} (pixels must stay square)"
            )
        return self.geometry.resized(h, w)


def scene_path(name_or_path: str | Path) -> Path:
    """Resolve a shipped scene name (``cios_fusion``) or a path to an XML file."""
    from scenes import SCENE_DIR, available

    p = Path(name_or_path)
    if p.suffix == ".xml" or p.exists():
        if not p.is_file():
            raise SceneError(f"scene file {p} does not exist")
        return p
    cand = SCENE_DIR / f"{name_or_path}.xml"
    if not cand.is_file():
        raise SceneError(f"unknown scene {str(name_or_path)!r}; shipped scenes: {', '.join(available())}")
    return cand


def load_scene(name_or_path: str | Path = DEFAULT_SCENE) -> CArmScene:
    """Read a scene file's C-arm geometry (no Mitsuba needed)."""
    path = scene_path(name_or_path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise SceneError(f"scene file {path} is not valid XML: {e}") from None
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}

    def number(key: str, kind=float, required: bool = True):
        if key not in defaults:
            if required:
                raise SceneError(f"scene file {path} lacks <default name=\"{key}\" value=...>")
            return None
        try:
            return kind(defaults[key])
        except ValueError:
            raise SceneError(f"scene file {path}: {key}={defaults[key]!r} is not a {kind.__name__}") from None

    try:
        geometry = CArmGeometry(
            sdd_mm=number("ctxreg_sdd_mm"),
            sod_mm=number("ctxreg_sod_mm"),
            height=number("ctxreg_detector_rows", int),
            width=number("ctxreg_detector_cols", int),
            pixel_spacing_mm=number("ctxreg_pixel_spacing_mm"),
            cx=number("ctxreg_cx", required=False),
            cy=number("ctxreg_cy", required=False),
        )
    except SceneError:
        raise
    except ValueError as e:
        raise SceneError(f"scene file {path}: invalid C-arm geometry: {e}") from None
    return CArmScene(path.stem, path, defaults.get("ctxreg_name", path.stem), geometry)


def sensor_values(geometry: CArmGeometry) -> dict[str, float | int]:
    """Mitsuba ``perspective`` sensor values for a geometry.

    Returns:
        ``width``, ``height`` (pixels), ``fov`` (horizontal, degrees) and the principal-point
        offsets ``ppx``, ``ppy`` (fractions of the film width / height; Mitsuba's image axes
        point opposite to the camera's x and y, hence the sign).
    """
    w, h = geometry.width, geometry.height
    cx, cy = geometry.principal_point
    fov = math.degrees(2.0 * math.atan(0.5 * w * geometry.pixel_spacing_mm / geometry.sdd_mm))
    return {
        "width": w,
        "height": h,
        "fov": fov,
        "ppx": ((w - 1) / 2.0 - cx) / w,
        "ppy": ((h - 1) / 2.0 - cy) / h,
    }


def load_mitsuba_scene(scene: CArmScene, geometry: CArmGeometry, *, ray_model: str = "siddon",
                       step_fraction: float = 0.5):
    """Load the scene file into Mitsuba for a geometry (render size) and ray model."""
    import mitsuba as mi

    ensure_variant()
    values = sensor_values(geometry)
    try:
        return mi.load_file(
            str(scene.path),
            ray_model=ray_model,
            step_fraction=str(step_fraction),
            **{k: str(v) for k, v in values.items()},
        )
    except RuntimeError as e:
        raise SceneError(f"Mitsuba could not load scene {scene.path}: {e}") from None
