"""The CT stage: a CT from its files to a volume the renderers take.

- :mod:`sim.ct.io`: NIfTI and DICOM series (and the built-in ``phantom``) to a volume, resampling;
- :mod:`sim.ct.cache`: a CT read once, kept as one uncompressed file with its anatomy centre;
- :mod:`sim.ct.volume`: :class:`sim.ct.volume.CTVolume` (HU and its voxel-to-LPS-mm affine);
- :mod:`sim.ct.anatomy`: the anatomy centre (a label map's centroid, else the pelvis's bone);
- :mod:`sim.ct.phantom`: the built-in pelvis phantom;
- :mod:`sim.ct.patients`: virtual patients, CTs deformed and varied from one.
"""
