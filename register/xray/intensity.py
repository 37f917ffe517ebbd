"""What an X-ray's pixel values mean: raw intensity, log or display-processed; bone bright or dark.

Registration compares an X-ray with DRRs, which are line integrals (bone bright, air ~ 0). An
X-ray arrives in one of three **scales** and either **polarity**:

* ``linear``: raw detector signal, proportional to the transmitted intensity ``I = I0 exp(-L)``
  (DICOM "FOR PROCESSING", Pixel Intensity Relationship ``LIN``); bone dark. Needs ``-log(I/I0)``.
* ``log``: log-processed, linear in the line integral (``LOG``).
* ``display``: a vendor's look-up table (window, gamma, edge enhancement) on top of a log image
  (``DISP``, a VOI LUT, fluoroscopy frames, JPEG/PNG exports). Monotone but unknown.

Polarity is stated for :attr:`register.xray.io.XRayImage.pixels` (which are already display-like:
MONOCHROME1 and an INVERSE presentation LUT are undone by the reader): ``bone-bright`` (a
radiograph) or ``bone-dark`` (a fluoroscopy frame, a raw image).

:func:`decide` weighs, in this order of strength (an option always wins):

1. **decisive DICOM tags**: Pixel Intensity Relationship (LIN / LOG / DISP) and its Sign (+1:
   larger stored value = more X-ray intensity = bone dark; -1: bone bright; flipped when the
   reader inverted the pixels), Presentation Intent "FOR PROCESSING" (raw: linear);
2. **the noise trend** (:func:`noise_trend`): quantum noise grows where fewer photons arrive, so in
   a linear image the noise grows with the value (Poisson, ``var ~ I``), in a bone-bright log or
   display image it grows with the value too (``var ~ 1/I``), and in a bone-dark display image it
   falls with the value. A falling trend means a bone-dark display image; a bone-dark image whose
   noise grows with its value is raw (linear);
3. **the image against the CT** (a :class:`PolarityReference`): the low-resolution, blurred X-ray
   correlated (NCC over the field) with line-integral DRRs of the CT at poses around the start;
   the polarity whose best correlation leads by :data:`REFERENCE_CLEAR`;
4. **conventions of the file**: a VOI LUT / window, the modality (fluoroscopy ``RF``/``XA``
   frames are shown bone dark; ``DX``/``CR``/``MG`` radiographs "FOR PRESENTATION" bone bright),
   8-bit exports (display);
5. a weaker CT reference (:data:`REFERENCE_MARGIN`), then the **centre contrast**
   (:func:`centre_contrast`): the middle of a field (the thickest path through the body)
   attenuates more than its rim in ~90 % of pelvis views.

``ctxreg register`` then checks the polarity against the CT unless an option or the Sign tag
set it (:func:`register.xray.prepare.confirm_polarity`).

The decision (:class:`IntensityDecision`) records every piece of evidence it saw and which one
decided, so that ``result.json`` can say why an image was log-corrected or inverted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from register.engines.metrics import ncc
from sim.core.errors import InputError
from sim.physics.display import TONE_LEVELS, TONES, apply_tone, quantile_curve

__all__ = [
    "SCALES",
    "POLARITIES",
    "IntensityError",
    "IntensityDecision",
    "PolarityReference",
    "decide",
    "noise_trend",
    "centre_contrast",
    "TONES",
    "TONE_LEVELS",
    "tone_curve",
    "apply_tone",
]

SCALES = ("linear", "log", "display")
POLARITIES = ("bone-bright", "bone-dark")

#: The polarity from the CT: the best correlation of one polarity leads the other's by at least
#: REFERENCE_CLEAR (NCC units: then it outranks the file's conventions) or REFERENCE_MARGIN (then
#: only the centre contrast ranks below it). Measured on 16 full-physics pelvis frames: the right
#: polarity led by 0.1-0.6 in 14, and by -0.04..0.05 in two views the 96 DRRs did not explain.
REFERENCE_CLEAR = 0.15
REFERENCE_MARGIN = 0.05
#: Rank correlation of noise against value at or below -NOISE_TREND_MIN: a bone-dark display image
#: (measured -0.35..-1.0 on 16 fluoroscopy frames, 70-120 kV; >= 0 on every raw, log and
#: bone-bright frame). At or above NOISE_TREND_LINEAR in a bone-dark image: raw (linear) data.
NOISE_TREND_MIN = 0.3
NOISE_TREND_LINEAR = 0.3
#: Noise below this fraction of the field's 1-99 % range is no noise (a noise-free image): 12-bit
#: display frames carry 1e-3 or more, a noise-free float image ~1e-6.
NOISE_FLOOR = 2e-4
#: Centre contrast (fraction of the field's 1-99 % range) needed to call a polarity from it.
CENTRE_MIN = 0.03

_DISPLAY_MODALITIES = ("RF", "XA")  # fluoroscopy / angiography frames: bone dark on screen
_RADIOGRAPH_MODALITIES = ("DX", "CR", "MG", "IO", "PX")  # radiographs for presentation: bone bright


class IntensityError(InputError):
    """A scale / polarity option or input cannot be used; the message names it."""


@dataclass(frozen=True)
class IntensityDecision:
    """How to read an X-ray's pixels.

    Attributes:
        scale: one of :data:`SCALES`.
        bone_bright: whether bone (attenuation) is bright in the pixels.
        scale_source / polarity_source: what decided (``"option"``, ``"DICOM ..."``, ``"CT
            reference"``, ``"image noise trend"``, ...).
        evidence: every observation, strongest first, as short sentences.
    """

    scale: str
    bone_bright: bool
    scale_source: str
    polarity_source: str
    evidence: tuple[str, ...] = ()

    @property
    def polarity(self) -> str:
        return "bone-bright" if self.bone_bright else "bone-dark"

    def steps(self) -> list[str]:
        """The preprocessing step names that make the pixels line-integral-like (bone bright).

        ``linear``: ``log`` (after ``invert`` when the intensity is shown inverted);
        otherwise ``invert`` when bone is dark; nothing for a bone-bright log / display image."""
        if self.scale == "linear":
            return ["invert", "log"] if self.bone_bright else ["log"]
        return [] if self.bone_bright else ["invert"]

    def to_dict(self) -> dict[str, Any]:
        return {"scale": self.scale, "polarity": self.polarity, "scale_source": self.scale_source,
                "polarity_source": self.polarity_source, "steps": self.steps(),
                "evidence": list(self.evidence)}


@dataclass(frozen=True)
class PolarityReference:
    """Line-integral DRRs of the CT for the polarity decision and the tone (:func:`tone_curve`):
    ``drrs`` ``(N, h, w)`` rendered with the X-ray's own detector geometry sampled at ``h x w``
    (see :func:`register.xray.prepare.reference_drrs`), and ``resample(image (H, W), mask (H, W)) ->
    (image (h, w), mask (h, w))`` bringing the X-ray to that sampling."""

    drrs: np.ndarray
    resample: Any = field(repr=False, default=None)
    blur_px: float = 1.0

    def scores(self, image: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
        """``(best NCC, best NCC of the inverted image)`` over the DRRs, within the mask."""
        small, small_mask = self.resample(image, mask)
        if small_mask is None or small_mask.sum() < 16:
            return 0.0, 0.0
        f = ndimage.gaussian_filter(small, self.blur_px)
        m = np.stack([ndimage.gaussian_filter(d, self.blur_px) for d in self.drrs])
        r = ncc(f, m, mask=small_mask)
        return float(r.max()), float(-r.min())

    def field_values(self, mask: np.ndarray) -> np.ndarray:
        """The DRRs' line integrals (dimensionless, sum of mu x length) inside the X-ray's field
        ``mask`` ``(H, W)`` (resampled to the DRRs' sampling), pooled over every pose: ``(n,)``."""
        _, small_mask = self.resample(np.zeros(np.shape(mask)), np.asarray(mask, bool))
        if small_mask is None:
            return self.drrs.reshape(-1)
        return self.drrs[:, small_mask].reshape(-1)


# ------------------------------------------------------------------------------------- tone

#: A tone curve needs at least this many reference DRR pixels inside the field (all poses together).
TONE_MIN_PIXELS = 256


def tone_curve(reference: PolarityReference, mask: np.ndarray | None, shape: tuple[int, int],
               levels: int = TONE_LEVELS) -> np.ndarray | None:
    """The values a display image's pixels are mapped onto: ``(levels,)`` quantiles (probabilities
    ``linspace(0, 1, levels)``) of the CT's line-integral DRRs inside the X-ray's field, pooled over
    the reference poses around the start (:attr:`PolarityReference.drrs`).

    A display chain (window, gamma, log or not, a vendor's LUT) is a monotone map of the line
    integral that the image does not state. Mapping the field's pixels by rank onto these quantiles
    (:func:`apply_tone`: histogram specification) undoes any such map up to the difference between
    the reference poses' histogram and the true view's, so that gradients compare with the DRR's at
    the right strength everywhere in the field (a gamma 2.6 display, or a linear one where the body
    sits in the lowest grey levels, otherwise hides most of them). ``mask`` ``(H, W)`` bool of the
    image of ``shape`` (None: every pixel). None when the field holds fewer than
    :data:`TONE_MIN_PIXELS` reference pixels.
    """
    m = np.ones(shape, bool) if mask is None else np.asarray(mask, bool)
    values = reference.field_values(m)
    if values.size < TONE_MIN_PIXELS:
        return None
    return quantile_curve(values, levels)


# ------------------------------------------------------------------------------------- cues


def noise_trend(image: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    """Spearman rank correlation of the local noise level with the local value, over the mask.

    The noise is the response to Immerkaer's 3 x 3 mask (the product of two second differences,
    divided by its norm 6: it cancels every linear and quadratic trend, so smooth anatomy does
    not count as noise), taken in the flatter half of the field (edges excluded); the field is
    split into 10 value deciles and the robust (MAD) noise of each decile is ranked against its
    mean value. Returns ``None`` when the image has no measurable noise (a noise-free simulation,
    heavy smoothing): the median noise below half a grey level of its value steps, or below
    :data:`NOISE_FLOOR` of its 1-99 % range.
    """
    img = np.asarray(image, np.float64)
    m = np.ones(img.shape, bool) if mask is None else ndimage.binary_erosion(mask, iterations=3)
    if m.sum() < 500:
        return None
    kernel = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]]) / 6.0
    resid = ndimage.convolve(img, kernel, mode="nearest")
    level = ndimage.uniform_filter(img, 7, mode="nearest")
    grad = ndimage.gaussian_gradient_magnitude(img, 1.5)
    keep = m & (grad <= np.percentile(grad[m], 50))
    if keep.sum() < 200:
        return None
    lv, rv = level[keep], resid[keep]
    edges = np.percentile(lv, np.linspace(0, 100, 11))
    means, spreads = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (lv >= lo) & (lv <= hi)
        if sel.sum() < 20:
            continue
        r = rv[sel]
        means.append(lv[sel].mean())
        spreads.append(1.4826 * np.median(np.abs(r - np.median(r))))
    if len(means) < 5:
        return None
    values = np.unique(img[m])
    step = float(np.median(np.diff(values))) if values.size > 1 else 0.0
    p1, p99 = np.percentile(img[m], [1, 99])
    noise = float(np.median(spreads))
    if noise <= 0 or noise < 0.5 * step or noise < NOISE_FLOOR * (p99 - p1):
        return None
    from scipy.stats import spearmanr

    rho = spearmanr(means, spreads).statistic
    return None if not np.isfinite(rho) else float(rho)


def centre_contrast(image: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Median of the field's middle (within 0.45 of its equivalent radius from its centroid)
    minus the median of its rim (0.65-0.95), in units of the field's 1-99 % range: > 0 when the
    middle is brighter."""
    img = np.asarray(image, np.float64)
    m = np.ones(img.shape, bool) if mask is None else mask
    rows, cols = np.nonzero(m)
    r0, c0 = rows.mean(), cols.mean()
    radius = np.sqrt(m.sum() / np.pi)
    rr, cc = np.indices(img.shape)
    d = np.hypot(rr - r0, cc - c0) / radius
    lo, hi = np.percentile(img[m], [1, 99])
    if not hi > lo:
        return 0.0
    mid = m & (d < 0.45)
    rim = m & (d > 0.65) & (d < 0.95)
    if mid.sum() < 10 or rim.sum() < 10:
        return 0.0
    return float((np.median(img[mid]) - np.median(img[rim])) / (hi - lo))


# ------------------------------------------------------------------------------------- tags


def _tag_evidence(tags: dict | None, inverted: bool) -> tuple[list, list, list, list]:
    """``(decisive scale, decisive polarity, weak scale, weak polarity)``: lists of
    ``(value, source, sentence)``; polarity values are ``bone_bright`` booleans for the pixels."""
    ds, dp, ws, wp = [], [], [], []
    if not tags:
        return ds, dp, ws, wp
    rel = (tags.get("PixelIntensityRelationship") or "").strip().upper()
    if rel in ("LIN", "LOG", "DISP"):
        scale = {"LIN": "linear", "LOG": "log", "DISP": "display"}[rel]
        ds.append((scale, "DICOM PixelIntensityRelationship", f"PixelIntensityRelationship {rel}: {scale}"))
    sign = tags.get("PixelIntensityRelationshipSign")
    if sign in (1, -1):
        # +1: larger stored value = more X-ray intensity = less attenuation = bone dark (stored)
        bright_stored = sign == -1
        bright = bright_stored != bool(inverted)
        dp.append((bright, "DICOM PixelIntensityRelationshipSign",
                   f"PixelIntensityRelationshipSign {sign:+d}" + (" (pixels inverted by the reader)" if inverted else "")
                   + f": bone {'bright' if bright else 'dark'}"))
    intent = (tags.get("PresentationIntentType") or "").strip().upper()
    if intent == "FOR PROCESSING":
        if not any(s == "DICOM PixelIntensityRelationship" for _, s, _ in ds):
            ds.append(("linear", "DICOM PresentationIntentType",
                       "PresentationIntentType FOR PROCESSING: raw detector values (linear)"))
        if not dp:
            wp.append((bool(inverted), "DICOM PresentationIntentType",
                       "PresentationIntentType FOR PROCESSING: raw values grow with the transmitted "
                       "intensity (bone dark)"))
    if tags.get("VOILUT"):
        ws.append(("display", "DICOM VOI LUT", "a VOI LUT / window is given: display-processed"))
    modality = (tags.get("Modality") or "").strip().upper()
    if modality in _DISPLAY_MODALITIES:
        ws.append(("display", "DICOM Modality", f"Modality {modality}: a fluoroscopy frame (display-processed)"))
        wp.append((False, "DICOM Modality", f"Modality {modality}: fluoroscopy is shown bone dark"))
    elif modality in _RADIOGRAPH_MODALITIES and intent != "FOR PROCESSING":
        ws.append(("display", "DICOM Modality", f"Modality {modality} for presentation: display-processed"))
        wp.append((True, "DICOM Modality", f"Modality {modality} for presentation: radiographs show bone bright"))
    return ds, dp, ws, wp


# ------------------------------------------------------------------------------------- decide


def decide(image: np.ndarray, mask: np.ndarray | None = None, *, tags: dict | None = None,
           inverted: bool = False, scale: str = "auto", polarity: str = "auto",
           reference: PolarityReference | None = None, bits: int | None = None) -> IntensityDecision:
    """Decide the scale and polarity of ``image`` ``(H, W)`` (valid pixels ``mask`` ``(H, W)`` bool).

    Args:
        tags: ``XRayImage.meta["intensity_tags"]`` (None for non-DICOM files).
        inverted: whether the reader inverted the stored values (MONOCHROME1 / INVERSE LUT).
        scale: ``"auto"`` or one of :data:`SCALES` (an option: wins over every cue).
        polarity: ``"auto"`` or one of :data:`POLARITIES` (an option).
        reference: DRRs of the CT for the polarity check (strong evidence), or None.
        bits: the stored bit depth when known (8-bit files are display exports).
    """
    if scale != "auto" and scale not in SCALES:
        raise IntensityError(f"scale must be 'auto' or one of {', '.join(SCALES)}, got {scale!r}")
    if polarity != "auto" and polarity not in POLARITIES:
        raise IntensityError(f"polarity must be 'auto' or one of {', '.join(POLARITIES)}, got {polarity!r}")
    img = np.asarray(image, np.float64)
    m = np.ones(img.shape, bool) if mask is None else np.asarray(mask, bool)
    evidence: list[str] = []
    d_scale, d_pol, w_scale, w_pol = _tag_evidence(tags, inverted)
    evidence += [s for _, _, s in d_scale + d_pol + w_scale + w_pol]
    if bits is not None and bits <= 8:
        w_scale.append(("display", "8-bit file", "8-bit values: a display export"))
        evidence.append("8-bit values: a display export")

    # ---- polarity: option > decisive tag > a falling noise trend > a clear CT reference > the
    # file's conventions > a weak CT reference > the centre contrast
    trend = noise_trend(img, m)
    evidence.append("noise trend: not measurable" if trend is None
                    else f"noise trend {trend:+.2f} (rank correlation of noise with value)")
    ref_margin, ref_bright = 0.0, None
    if reference is not None:
        pos, neg = reference.scores(img, m)
        evidence.append(f"CT reference: best NCC {pos:.2f} as given, {neg:.2f} inverted")
        ref_margin, ref_bright = abs(pos - neg), pos > neg
    centre = centre_contrast(img, m)
    evidence.append(f"centre contrast {centre:+.3f} (> 0: the field's middle is brighter)")
    if polarity != "auto":
        bright, pol_src = polarity == "bone-bright", "option"
    elif d_pol:
        bright, pol_src = d_pol[0][0], d_pol[0][1]
    elif trend is not None and trend <= -NOISE_TREND_MIN:
        bright, pol_src = False, "image noise trend (noise falls with the value: a bone-dark display image)"
    elif ref_bright is not None and ref_margin >= REFERENCE_CLEAR:
        bright, pol_src = ref_bright, "CT reference"
    elif w_pol:
        bright, pol_src = w_pol[0][0], w_pol[0][1]
    elif ref_bright is not None and ref_margin >= REFERENCE_MARGIN:
        bright, pol_src = ref_bright, "CT reference (weak)"
    elif abs(centre) >= CENTRE_MIN:
        bright, pol_src = centre > 0, "image centre contrast"
    else:
        bright, pol_src = True, "default (no evidence: bone bright assumed)"

    # ---- scale: option > decisive tag > the file's conventions > the image
    if scale != "auto":
        sc, sc_src = scale, "option"
    elif d_scale:
        sc, sc_src = d_scale[0][0], d_scale[0][1]
    elif w_scale:
        sc, sc_src = w_scale[0][0], w_scale[0][1]
    elif not bright and trend is not None and trend >= NOISE_TREND_LINEAR and img[m].min() >= 0:
        sc, sc_src = "linear", "image noise trend (bone dark, and noise grows with the value: Poisson)"
    else:
        sc, sc_src = "display", "default (a monotone display scale: no log)"
    if sc == "linear" and img[m].max() <= 0:
        raise IntensityError("the image is declared linear (raw intensity) but has no positive pixel values")
    return IntensityDecision(scale=sc, bone_bright=bool(bright), scale_source=sc_src, polarity_source=pol_src,
                             evidence=tuple(evidence))
