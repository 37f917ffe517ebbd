"""The C-arm geometry of an X-ray image, and where each of its values came from.

:func:`resolve_geometry` and :func:`geometry_for`: each of SDD, SOD and the detector pixel
pitch comes from the first of: an explicit argument (the CLI flags ``--sdd``, ``--sod``,
``--pixel-spacing``) > the DICOM tags > the scene (assumed). :func:`resolve_geometry` also says where
each value came from (:class:`GeometrySources`) and refuses tags that contradict each other.

DICOM tags read for the geometry (all lengths in mm; an empty tag counts as absent; the values are
kept in ``meta["geometry_tags"]``). A tag that is present but invalid (non-positive, non-finite,
malformed) is not used: its name is in ``meta["ignored_tags"]`` and its text in
``meta["invalid_tags"]``, and :func:`resolve_geometry` refuses the image naming the tag unless
the value it would give is given explicitly (``--sdd``, ``--sod``, ``--pixel-spacing``): a
broken tag is not silently replaced by the scene's value.

* ``DistanceSourceToDetector`` (0018,1110), SID/SDD: focal spot to the detector surface.
* ``DistanceSourceToPatient`` (0018,1111), SOD: focal spot to the patient (the isocentre, the
  plane where the C-arm model puts the object).
* ``EstimatedRadiographicMagnificationFactor`` (0018,1114), ERMF, dimensionless: the magnification
  of the object plane on the detector, ``SID / SOD`` (> 1).
* ``ImagerPixelSpacing`` (0018,1164), (row, column): pixel pitch **at the detector front plane**
  (after binning), which is what the C-arm model needs.
* ``DetectorElementSpacing`` (0018,7022), (row, column): pitch of the physical detector elements;
  ``ImagerPixelSpacing`` is this times an integer binning factor (>= 1).
* ``PixelSpacing`` (0028,0030), (row, column): pitch "in the patient"; for DX/CR it may be
  calibrated to the patient plane, i.e. ``ImagerPixelSpacing / ERMF`` ...
* ``PixelSpacingCalibrationType`` (0028,0A02): ... which this tag says (``GEOMETRY``: from the
  ERMF, ``FIDUCIAL``: from an object of known size); when present, ``PixelSpacing x ERMF`` gives
  the pitch at the detector back.

``XRayImage.sdd_mm`` / ``sod_mm`` hold ``DistanceSourceToDetector`` / ``DistanceSourceToPatient`` as
written, and ``XRayImage.pixel_spacing_mm`` the first of ``ImagerPixelSpacing``, ``PixelSpacing``
(``meta["pixel_spacing_tag"]`` says which) as written; anisotropic spacing is kept out of
``pixel_spacing_mm`` (``None``, the pair in ``meta["pixel_spacing_rc_mm"]``) and the geometry then
asks for an explicit square spacing. Derived values (SOD from ERMF, spacing from PixelSpacing x
ERMF) are made by :func:`resolve_geometry` only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from register.xray.io import _ERMF, XRayImage, XRayInputError, _is_square, _positive
from sim.projection.geometry import CArmGeometry
from sim.projection.scene import load_scene

__all__ = ["GeometrySources", "resolve_geometry", "geometry_for"]

#: ``EstimatedRadiographicMagnificationFactor`` may differ from ``SDD / SOD`` by this fraction.
_ERMF_RTOL = 0.02
#: ``ImagerPixelSpacing`` may be this fraction below ``DetectorElementSpacing`` (rounding) ...
_BIN_BELOW_RTOL = 0.01
#: ... and this fraction away from an integer multiple (binning factor) of it.
_BIN_RTOL = 0.02
#: The explicit arguments of :func:`resolve_geometry` by their command-line flags.
_FLAGS = {"sdd_mm": "--sdd", "sod_mm": "--sod", "pixel_spacing_mm": "--pixel-spacing"}


@dataclass(frozen=True)
class GeometrySources:
    """The geometry values :func:`resolve_geometry` chose and where each came from.

    Attributes:
        sdd_mm: source-to-detector distance (mm).
        sdd_source: where it came from, e.g. ``"flag --sdd"``, ``"DICOM DistanceSourceToDetector"``,
            ``"scene 'cios_fusion' (assumed)"``.
        sod_mm: source-to-patient (isocentre) distance (mm).
        sod_source: e.g. ``"flag --sod"``, ``"DICOM DistanceSourceToPatient"``, ``"DICOM
            DistanceSourceToDetector / EstimatedRadiographicMagnificationFactor"`` (derived),
            ``"scene 'cios_fusion' (assumed)"``.
        pixel_spacing_mm: detector pixel pitch (mm) at the image's own resolution (before any
            ``size`` resampling).
        pixel_spacing_source: e.g. ``"flag --pixel-spacing"``, ``"DICOM ImagerPixelSpacing"``,
            ``"DICOM DetectorElementSpacing"``, ``"DICOM PixelSpacing x
            EstimatedRadiographicMagnificationFactor"``, ``"DICOM PixelSpacing"``, ``"scene
            'cios_fusion' (assumed)"``.
        notes: remarks that are not errors (e.g. a patient-plane PixelSpacing without ERMF).
    """

    sdd_mm: float
    sdd_source: str
    sod_mm: float
    sod_source: str
    pixel_spacing_mm: float
    pixel_spacing_source: str
    notes: tuple[str, ...] = ()

    @property
    def assumed(self) -> list[str]:
        """Names (``sdd_mm``, ``sod_mm``, ``pixel_spacing_mm``) of values that rest on the scene."""
        return [name for name, src in self._items() if "(assumed)" in src]

    def _items(self) -> list[tuple[str, str]]:
        return [
            ("sdd_mm", self.sdd_source),
            ("sod_mm", self.sod_source),
            ("pixel_spacing_mm", self.pixel_spacing_source),
        ]

    def line(self) -> str:
        """One line for a log, e.g. ``geometry: SDD 1020 mm (DICOM DistanceSourceToDetector), SOD 510
        mm (scene 'cios_fusion' (assumed)), pixel 0.300 mm (DICOM ImagerPixelSpacing)``."""
        text = (
            f"geometry: SDD {self.sdd_mm:g} mm ({self.sdd_source}), SOD {self.sod_mm:g} mm ({self.sod_source}), "
            f"pixel {self.pixel_spacing_mm:.3f} mm ({self.pixel_spacing_source})"
        )
        return " ".join(text.split())  # one line whatever a scene path holds

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable: the values (mm), their sources, ``assumed`` and ``notes``."""
        return {
            "sdd_mm": self.sdd_mm,
            "sdd_source": self.sdd_source,
            "sod_mm": self.sod_mm,
            "sod_source": self.sod_source,
            "pixel_spacing_mm": self.pixel_spacing_mm,
            "pixel_spacing_source": self.pixel_spacing_source,
            "assumed": self.assumed,
            "notes": list(self.notes),
        }


def _fmt_rc(rc: list[float] | tuple[float, float]) -> str:
    return f"{rc[0]:g} x {rc[1]:g} mm" if not _is_square(rc) else f"{rc[0]:g} mm"


def _check_binning(src: str, imager: list[float], element: list[float]) -> None:
    """``ImagerPixelSpacing`` must be an integer multiple (>= 1) of ``DetectorElementSpacing``."""
    for axis, ip, de in zip(("row", "column"), imager, element):
        ratio = ip / de
        if ratio < 1.0 - _BIN_BELOW_RTOL:
            raise XRayInputError(
                f"{src}: ImagerPixelSpacing {_fmt_rc(imager)} is smaller than DetectorElementSpacing "
                f"{_fmt_rc(element)} ({axis} ratio {ratio:.4g} < 1 by more than {_BIN_BELOW_RTOL:.0%}); "
                f"pass --pixel-spacing to choose"
            )
        n = max(1, round(ratio))
        if abs(ratio - n) > _BIN_RTOL * n:
            raise XRayInputError(
                f"{src}: ImagerPixelSpacing {_fmt_rc(imager)} is not an integer multiple (binning) of "
                f"DetectorElementSpacing {_fmt_rc(element)} ({axis} ratio {ratio:.4g}, {abs(ratio - n) / n:.1%} "
                f"from {n}, more than {_BIN_RTOL:.0%}); pass --pixel-spacing to choose"
            )


#: The flag that gives the value of each geometry tag instead (:func:`resolve_geometry`'s argument).
_TAG_FLAGS = {"DistanceSourceToDetector": "sdd_mm", "DistanceSourceToPatient": "sod_mm", _ERMF: "sod_mm",
              "ImagerPixelSpacing": "pixel_spacing_mm", "DetectorElementSpacing": "pixel_spacing_mm",
              "PixelSpacing": "pixel_spacing_mm"}


def _refuse_invalid_tags(src: str, meta: dict, **explicit: float | None) -> None:
    """Raise :class:`XRayInputError` naming the geometry tags that are present but invalid (see the
    module docstring), unless the value each would give is ``explicit`` (a flag)."""
    invalid = meta.get("invalid_tags")
    if not isinstance(invalid, dict):
        invalid = {k: None for k in meta.get("ignored_tags") or ()}
    bad = [(tag, text) for tag, text in invalid.items() if explicit.get(_TAG_FLAGS.get(tag, "")) is None]
    if bad:
        items = ", ".join(f"{tag} = {text}" if text is not None else tag for tag, text in bad)
        flags = " / ".join(dict.fromkeys(_FLAGS[_TAG_FLAGS[tag]] for tag, _ in bad if tag in _TAG_FLAGS))
        raise XRayInputError(
            f"{src}: invalid DICOM geometry tag{'s' if len(bad) > 1 else ''} {items} (a positive number of mm, "
            f"or a pair for a spacing, is needed); give the value{'s' if len(bad) > 1 else ''} with {flags}"
        )


def resolve_geometry(
    xray: XRayImage,
    scene: str | os.PathLike | None = "cios_fusion",
    *,
    size: tuple[int, int] | None = None,
    sdd_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_spacing_mm: float | None = None,
) -> tuple[CArmGeometry, GeometrySources]:
    """The C-arm geometry of ``xray``'s detector and where each of its values came from.

    Args:
        xray: the image; its DICOM tags are read from ``meta["geometry_tags"]`` (see the module
            docstring); an image without them (PNG, ``.npy``, built by hand) offers its
            ``sdd_mm`` / ``sod_mm`` / ``pixel_spacing_mm`` fields instead (source ``"XRayImage.<name>"``).
        scene: scene name or file for the fallback values (``None`` = no fallback).
        size: ``(H, W)`` to resample the detector to (keeps the physical extent and must keep the
            aspect ratio); ``None`` = the image's own pixels.
        sdd_mm, sod_mm, pixel_spacing_mm: explicit values in mm (the CLI flags ``--sdd``, ``--sod``,
            ``--pixel-spacing``); each overrides the tags on purpose and is reported as the flag.

    Order, per value (the first that applies):

    * SDD: flag > ``DistanceSourceToDetector`` > scene.
    * SOD: flag > ``DistanceSourceToPatient`` > ``SDD / EstimatedRadiographicMagnificationFactor``
      (SDD as resolved above, the source says from where) > scene.
    * Pixel pitch at the detector: flag > ``ImagerPixelSpacing`` > ``DetectorElementSpacing`` >
      ``PixelSpacing x ERMF`` when ``PixelSpacingCalibrationType`` is present (PixelSpacing is then
      calibrated to the patient plane) > ``PixelSpacing`` > scene (``scene detector width / W``,
      only when the image's aspect ``H / W`` matches the scene detector's to within one pixel).

    The detector has the image's ``H x W`` pixels and the default principal point (the centre).

    Raises:
        XRayInputError (one line, naming both tags / values) when a geometry tag is present but
        invalid (``meta["invalid_tags"]``) and its value is not given explicitly; a value is missing
        and there is no fallback; the chosen spacing tag is anisotropic; the final SOD >= SDD (from any sources);
        ``DistanceSourceToDetector / DistanceSourceToPatient`` and ERMF differ by more than 2 %
        (neither distance given as a flag); an ERMF < 1 is used; ``ImagerPixelSpacing`` is more than
        1 % below ``DetectorElementSpacing`` or more than 2 % from an integer multiple of it (no
        ``--pixel-spacing``). A flag never counts as a contradiction of a tag.
    """
    if not isinstance(xray, XRayImage):
        raise XRayInputError(f"xray: expected an XRayImage, got {type(xray).__name__}")
    src = xray.source or "X-ray image"
    H, W = xray.shape
    sc = None
    scene_src = ""
    if scene is not None:
        sc = load_scene(scene).geometry
        scene_src = f"scene {os.fspath(scene)!r} (assumed)"
    meta = xray.meta if isinstance(xray.meta, dict) else {}
    tags = meta.get("geometry_tags") if isinstance(meta.get("geometry_tags"), dict) else None
    notes: list[str] = []
    _refuse_invalid_tags(src, meta, sdd_mm=sdd_mm, sod_mm=sod_mm, pixel_spacing_mm=pixel_spacing_mm)

    def explicit(name: str, value: object) -> tuple[float, str] | None:
        if value is None:
            return None
        return _positive(value, f"{name} ({_FLAGS[name]})"), f"flag {_FLAGS[name]}"

    def missing(name: str) -> XRayInputError:
        return XRayInputError(
            f"{src}: no {name} - the image has none and no scene was given; pass {name} explicitly "
            f"({_FLAGS[name]}) or a scene"
        )

    # DICOM values (or an image's own fields when it has no DICOM tags)
    if tags is not None:
        t_sdd = tags.get("DistanceSourceToDetector")
        t_sod = tags.get("DistanceSourceToPatient")
        ermf = tags.get(_ERMF)
        img_sdd = (t_sdd, "DICOM DistanceSourceToDetector") if t_sdd else None
        img_sod = (t_sod, "DICOM DistanceSourceToPatient") if t_sod else None
    else:
        t_sdd = t_sod = ermf = None
        img_sdd = (xray.sdd_mm, "XRayImage.sdd_mm") if xray.sdd_mm else None
        img_sod = (xray.sod_mm, "XRayImage.sod_mm") if xray.sod_mm else None
    scene_sdd = (sc.sdd_mm, scene_src) if sc else None
    scene_sod = (sc.sod_mm, scene_src) if sc else None

    # tag-against-tag check (a flag for either distance settles it)
    if sdd_mm is None and sod_mm is None and t_sdd and t_sod and ermf:
        ratio = t_sdd / t_sod
        rel = abs(ermf - ratio) / ratio
        if rel > _ERMF_RTOL:
            raise XRayInputError(
                f"{src}: {_ERMF} {ermf:g} contradicts DistanceSourceToDetector / DistanceSourceToPatient "
                f"= {t_sdd:g} / {t_sod:g} = {ratio:.4g} (relative difference {rel:.1%} > {_ERMF_RTOL:.0%}); "
                f"pass --sdd / --sod to choose"
            )

    def usable_ermf(purpose: str) -> float:
        assert ermf is not None
        if ermf < 1.0:
            raise XRayInputError(
                f"{src}: {_ERMF} {ermf:g} < 1 is impossible (it is SID / SOD > 1); cannot use it for "
                f"{purpose}; pass {'--sod' if purpose == 'SOD' else '--pixel-spacing'}"
            )
        return ermf

    sdd, sdd_src = explicit("sdd_mm", sdd_mm) or img_sdd or scene_sdd or (None, "")
    if sdd is None:
        raise missing("sdd_mm")
    sod_pick = explicit("sod_mm", sod_mm) or img_sod
    if sod_pick is None and ermf:
        m = usable_ermf("SOD")
        # "DICOM DistanceSourceToDetector / ERMF", "flag --sdd / DICOM ERMF", "scene ... / DICOM ERMF"
        via = f"{sdd_src} / {_ERMF}" if sdd_src.startswith("DICOM ") else f"{sdd_src} / DICOM {_ERMF}"
        sod_pick = (sdd / m, via)
    sod, sod_src = sod_pick or scene_sod or (None, "")
    if sod is None:
        raise missing("sod_mm")

    # pixel pitch at the detector
    spacing: float | None = None
    spacing_src = ""
    chosen: tuple[str, list[float]] | None = None  # (tag, [row, col]) when read from the file
    if pixel_spacing_mm is not None:
        spacing, spacing_src = explicit("pixel_spacing_mm", pixel_spacing_mm)  # type: ignore[misc]
    elif tags is not None:
        ips, des = tags.get("ImagerPixelSpacing"), tags.get("DetectorElementSpacing")
        ps, calib = tags.get("PixelSpacing"), tags.get("PixelSpacingCalibrationType")
        if ips and des:
            _check_binning(src, ips, des)
        if ips:
            chosen, spacing_src = ("ImagerPixelSpacing", ips), "DICOM ImagerPixelSpacing"
        elif des:
            chosen, spacing_src = ("DetectorElementSpacing", des), "DICOM DetectorElementSpacing"
        elif ps and calib and ermf:
            m = usable_ermf("the pixel spacing")
            chosen = ("PixelSpacing", [ps[0] * m, ps[1] * m])
            spacing_src = f"DICOM PixelSpacing x {_ERMF}"
        elif ps:
            chosen, spacing_src = ("PixelSpacing", ps), "DICOM PixelSpacing"
            if calib:
                notes.append(
                    f"PixelSpacing is calibrated to the patient plane (PixelSpacingCalibrationType "
                    f"{calib}) but there is no {_ERMF}: used as the detector pitch"
                )
        if chosen is not None:
            rc = chosen[1]
            if not _is_square(rc):
                raise XRayInputError(
                    f"{src}: no usable pixel_spacing_mm - {chosen[0]} is anisotropic {list(rc)} mm "
                    f"(row, col); pass a square pixel_spacing_mm (--pixel-spacing) after resampling the "
                    f"image to square pixels"
                )
            spacing = 0.5 * (rc[0] + rc[1])
    elif xray.pixel_spacing_mm is not None:
        spacing, spacing_src = xray.pixel_spacing_mm, "XRayImage.pixel_spacing_mm"
    elif meta.get("pixel_spacing_anisotropic"):
        raise XRayInputError(
            f"{src}: no usable pixel_spacing_mm - {meta.get('pixel_spacing_tag')} is anisotropic "
            f"{meta.get('pixel_spacing_rc_mm')} mm (row, col); pass a square pixel_spacing_mm "
            f"(--pixel-spacing) after resampling the image to square pixels"
        )
    if spacing is None:
        if sc is None:
            raise missing("pixel_spacing_mm")
        scene_aspect = sc.height / sc.width
        if abs(H / W - scene_aspect) * min(H, W) > 1.0:
            raise XRayInputError(
                f"{src}: no pixel_spacing_mm - the image has none and its {H} x {W} pixels do not "
                f"match the aspect of the scene detector ({sc.height} x {sc.width}); pass "
                f"pixel_spacing_mm explicitly (--pixel-spacing)"
            )
        spacing, spacing_src = sc.detector_size_mm[1] / W, scene_src

    if not 0 < sod < sdd:
        raise XRayInputError(
            f"{src}: SOD {sod:g} mm ({sod_src}) >= SDD {sdd:g} mm ({sdd_src}); the geometry needs "
            f"0 < sod_mm < sdd_mm (the patient lies between source and detector)"
        )
    geom = CArmGeometry(sdd_mm=sdd, sod_mm=sod, height=H, width=W, pixel_spacing_mm=spacing)
    if size is not None:
        try:
            h, w = (int(size[0]), int(size[1]))
        except (TypeError, ValueError, IndexError):
            raise XRayInputError(f"size: expected (height, width) in pixels, got {size!r}") from None
        if (h, w) != (H, W):
            try:
                geom = geom.resized(h, w)
            except ValueError as e:
                raise XRayInputError(f"size: {e}") from None
    sources = GeometrySources(float(sdd), sdd_src, float(sod), sod_src, float(spacing), spacing_src, tuple(notes))
    return geom, sources


def geometry_for(
    xray: XRayImage,
    scene: str | os.PathLike | None = "cios_fusion",
    *,
    size: tuple[int, int] | None = None,
    sdd_mm: float | None = None,
    sod_mm: float | None = None,
    pixel_spacing_mm: float | None = None,
) -> CArmGeometry:
    """The C-arm geometry of ``xray``'s detector: :func:`resolve_geometry` without the sources.

    SDD, SOD and the pixel spacing (mm) each come from the explicit argument, else the image's DICOM
    tags, else the scene (``None`` = no scene); ``size = (H, W)`` resamples the detector keeping its
    physical extent. Raises :class:`XRayInputError` as :func:`resolve_geometry` does.
    """
    return resolve_geometry(
        xray, scene, size=size, sdd_mm=sdd_mm, sod_mm=sod_mm, pixel_spacing_mm=pixel_spacing_mm
    )[0]
