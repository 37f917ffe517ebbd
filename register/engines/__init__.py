"""Registration engines: a prepared X-ray to a pose.

``result`` (what every engine returns, its error), ``metrics`` (image similarity), ``cmaes``
(multi-resolution CMA-ES), ``search`` (the global search), ``contextual`` (the network's pose
iteration), ``pipeline`` (contextual + global search + CMA-ES refinement as one object),
``methods`` (the methods by name, built in one place). The bottom layer of :mod:`register`: it
imports nothing else of it.
"""
