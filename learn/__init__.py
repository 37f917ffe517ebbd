"""ctxreg.learn: the contextual pose-update network (PyTorch). Imports :mod:`sim`, never the reverse."""
