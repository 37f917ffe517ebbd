"""Temporary: the old path of :mod:`register.xray.intensity` until preprocess.py moves (issue 30)."""
from register.xray.intensity import POLARITIES, SCALES, TONE_LEVELS, TONES, PolarityReference, decide, tone_curve  # noqa: F401
