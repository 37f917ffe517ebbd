"""ctxreg.register: pose estimation of X-rays against a CT, evaluation, and the ``ctxreg`` CLI."""
