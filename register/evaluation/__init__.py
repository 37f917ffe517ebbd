"""Registered poses against a known truth: errors, the evaluation protocol, studies and the demo.

``errors`` (pose errors against the truth), ``frames`` (the realistic frame simulator),
``evaluate`` (the evaluation protocol), ``study`` (the domain-gap study), ``xray_study``
(collimated against open frames), ``demo`` (``ctxreg demo``).
"""
