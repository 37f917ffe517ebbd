"""ctxreg.register: pose estimation of X-rays against a CT, evaluation, and the ``ctxreg`` CLI.

The public API (README "Python API")::

    from register import register_xray
    result = register_xray(ct, "xray.dcm", method="cmaes")   # or method="contextual+cmaes", model="..."

    from register import RegistrationRequest                 # one request, many X-rays of a case
    request = RegistrationRequest(method="contextual+cmaes", model="pelvis_xray")
    results = [request.run(ct, f) for f in ("frame1.dcm", "frame2.dcm")]

:func:`register.api.register_xray` does what ``ctxreg register`` does and returns an
:class:`register.api.XRayRegistration` (pose, similarity, the prepared X-ray, ``write(out)``).
It is imported on first use, so ``import register`` stays cheap.
"""

__all__ = ["register_xray", "RegistrationRequest", "XRayRegistration"]


def __getattr__(name: str):
    if name in __all__:
        from register import api  # local: the name is one of this module's own

        return getattr(api, name)
    raise AttributeError(f"module 'register' has no attribute {name!r}")
