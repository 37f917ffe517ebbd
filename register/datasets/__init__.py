"""Public data sets of X-rays with a CT and a ground-truth pose, read into ctxreg's terms.

``deepfluoro`` (the DeepFluoro full-resolution HDF5 file of Grupp et al. 2020: reader and writer of
its layout), ``deepfluoro_synthetic`` (a file of that layout made from a CT, with frames rendered by
ctxreg at known poses: the reader's and the evaluation's test bed).
"""
