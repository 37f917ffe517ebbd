"""The X-ray's way in: a file to the prepared image the engines register.

``io`` (reading and writing X-ray files), ``geometry`` (the C-arm geometry of an X-ray and where
each value came from), ``field`` (the collimated field), ``intensity`` (raw / log / display, bone
bright or dark, tone), ``preprocess`` (the preprocessing steps), ``prepare`` (all of it, to the
optimiser's size, and the polarity check against the CT), ``network_view`` (what a
detector-framed network sees of the prepared X-ray). It sits above :mod:`register.engines`: the
polarity check and the intensity decision score the X-ray against DRRs of the CT with the
engines' similarity and global search.
"""
