"""ctxreg.sim: X-ray simulation from CT with Mitsuba 3 / Dr.Jit.

Importing :mod:`sim` locates a libLLVM >= 16 for Dr.Jit's CPU backend (see :mod:`sim.projection.llvm`)
before any Dr.Jit kernel can run. NumPy-only modules (:mod:`sim.projection.se3`, :mod:`sim.projection.geometry`,
:mod:`sim.ct`, :mod:`sim.ct.phantom`) never import Dr.Jit; :mod:`sim.projection.backend` does.

The public API (README "Python API")::

    from sim import load_ct, render
    ct = load_ct("pelvis.nii.gz")                    # or "phantom"
    drr = render(ct, pose=[20, -10, 0, 0, 0, 0], size=(256, 256), physics="poly")

:func:`load_ct` returns a :class:`sim.ct.volume.CTVolume`; :func:`sim.render.render` an ``(H, W)``
float32 image. ``import sim`` stays cheap: both import their modules when first used.
"""

from sim.projection import llvm as _llvm
from sim.ct.volume import CTInputError, CTVolume

_llvm.configure()

__version__ = "0.1.0"
__all__ = ["load_ct", "render", "__version__"]


def load_ct(ct, *, label_map=None, resample_mm=None, cache=False, log=None):
    """A CT as a :class:`sim.ct.volume.CTVolume` (HU float32 ``(I, J, K)`` and its voxel-to-LPS-mm affine).

    Args:
        ct: a NIfTI file (``.nii`` / ``.nii.gz``), a folder holding one DICOM series,
            ``"phantom"`` / ``"phantom:SEED"`` (the built-in pelvis phantom, 2 mm voxels), or a
            :class:`~sim.ct.volume.CTVolume` (returned as it is).
        label_map: a label volume on the CT's grid (NIfTI or DICOM folder); its centroid becomes the
            default anatomy centre, and ``--label-material`` style overrides use it.
        resample_mm: a new voxel spacing in mm (one value or three, along i, j, k).
        cache: read a CT file or series through the CT cache (:mod:`sim.ct.cache`: once read, a CT
            loads from one uncompressed file with its anatomy centre; a changed CT misses):
            False (default) reads the files, True uses the default cache folder, a path that
            folder. Not used with a label map, the phantom or a CTVolume.
        log: with ``cache``, called with a line where an entry is written or rebuilt.

    Raises :class:`sim.ct.volume.CTInputError` (an :class:`sim.core.errors.InputError`) naming the file and
    the problem.
    """
    from sim.ct.io import is_phantom_spec, load_ct_spec, resample  # loads SciPy: imported where first needed (start-up)

    if isinstance(ct, CTVolume) and label_map is not None:
        raise CTInputError(f"{ct.source}: a loaded CTVolume keeps its own labels; load the CT with label_map=...")
    if cache and label_map is None and not isinstance(ct, CTVolume) and not is_phantom_spec(ct):
        from sim.ct.cache import load_ct_cached  # loads SciPy: imported where first needed (start-up)

        volume = load_ct_cached(ct, cache_dir=None if cache is True else cache, log=log)
    else:
        volume = ct if isinstance(ct, CTVolume) else load_ct_spec(ct, label_map=label_map)
    return volume if resample_mm is None else resample(volume, resample_mm)


def __getattr__(name: str):
    # ``sim.render`` is a module that is also callable (:func:`sim.render.render`); importing it on
    # first use keeps ``import sim`` cheap.
    if name == "render":
        import importlib

        return importlib.import_module("sim.render")
    raise AttributeError(f"module 'sim' has no attribute {name!r}")
