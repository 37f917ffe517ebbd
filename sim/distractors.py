"""Distractors in the field: surgical tools and equipment as triangle meshes, traced by Mitsuba.

A realistic intra-operative X-ray shows more than the patient: screws, K-wires, plates and
retractors, the table and cables. This module makes them as closed triangle meshes, places
them independently of the anatomy, measures per pixel how far each ray of a C-arm view runs
inside them (with Mitsuba's own ray intersection), and adds their attenuation at every physics
level.

Tools (each a :class:`ToolMesh` in its own local frame, mm, made with pymeshlab's primitives
and booleans, or swept in NumPy for tubes, then cleaned by :func:`clean_mesh`):

==============  =========================================================  ===================
builder         shape (local frame)                                        default material
==============  =========================================================  ===================
:func:`screw`   shaft (z from the tip 0 to ``length_mm``), conical tip,     titanium
                cylindrical head above the shaft
:func:`k_wire`  cylinder along z from 0 to ``length_mm`` (1.6-2.5 mm)       stainless_steel
:func:`plate`   box ``length x width x thickness`` (x, y, z) centred, with  titanium
                round holes along x
:func:`retractor`  handle box along -x and a blade bent by ``bend_deg``     stainless_steel
                about y at the origin
:func:`table`   slab ``width x length x thickness`` (x, y, z) centred       carbon, 0.2 g/cm^3
:func:`cable`   tube along a 3-D path: a copper core and a PVC sheath       copper + pvc
                (two meshes: the sheath is hollow)
==============  =========================================================  ===================

A :class:`Distractor` is a tool with a pose: a ``(4, 4)`` map from the tool's frame to the CT's
LPS frame (``frame="lps"``: the tool moves with the patient when the C-arm pose changes, as a
screw or a retractor does), or to the camera frame (``frame="camera"``: fixed to the C-arm, for
example a table seen the same way in every view, or a cable hanging from the detector). Poses
are the tools' own: nothing in the CT places them.

Chords (:class:`DistractorField`): the pixel-centre rays are made by the renderer's own code
(the ``ctxreg_drr`` integrator's ray generation from the scene's Mitsuba sensor, placed by
:func:`sim.projection.geometry.extrinsic_lps_to_camera` for each pose), and the meshes are put in a Mitsuba
scene, one per channel (material and density). Per ray a symbolic ``dr.while_loop`` calls
``scene.ray_intersect`` repeatedly: an entry (``d . n < 0`` for the outward face normal ``n``)
subtracts its distance ``t``, an exit adds it, so the sum is the total length inside the closed
meshes, overlapping tools included (their lengths add). The next search starts
:data:`SKIP_MM` past the hit, so a ray through an edge shared by two faces counts once. A ray
that only touches a silhouette edge may report an entry without its exit (or the reverse): an
exit with nothing open is dropped, and an entry still open at the end is closed at the ray's last
hit of that channel (``unpaired_rays`` counts such rays; zero in the tests).

Attenuation:

* ``line``: ``L += mu(E_line) * chord`` with ``mu`` from xraylib at :data:`LINE_ENERGY_KEV`
  (60 keV, the energy of :data:`sim.physics.materials.MU_WATER_60KEV_PER_MM`) at the tool's density
  (:func:`add_to_line_integral`);
* ``poly`` / ``full``: the tool's density line integral ``rho * chord / 10`` (g/cm^2) is added
  to the channel of its material, appended when the CT's decomposition lacks it
  (:func:`add_to_density_integrals`). The Monte Carlo scatter of ``full`` still sees the CT
  only: the tools attenuate the primary, they do not scatter.

:class:`RendererWithDistractors` and :func:`imager_with_distractors` wrap a
:class:`sim.projection.drr.DRRRenderer` or a :class:`sim.physics.imaging.XRayImager` so that their
``render`` includes the tools; without tools the wrapped objects are untouched.

Units: mm, g/cm^3, g/cm^2, 1/mm, keV.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from sim.core.errors import InputError
from sim.physics.materials import MATERIALS, mu_linear, nominal_density
from sim.physics.poly import Polychromatic
from sim.projection.drr import DRRRenderer, MAX_RAYS_PER_LAUNCH, camera_from_sensor
from sim.projection.geometry import CArmGeometry, extrinsic_lps_to_camera
from sim.projection.scene import DEFAULT_SCENE, load_mitsuba_scene, load_scene

__all__ = [
    "DistractorError",
    "random_tools",
    "implanted_tools",
    "ToolMesh",
    "Distractor",
    "DistractorField",
    "RendererWithDistractors",
    "clean_mesh",
    "screw",
    "k_wire",
    "plate",
    "retractor",
    "table",
    "cable",
    "mu_line",
    "add_to_line_integral",
    "add_to_density_integrals",
    "imager_with_distractors",
    "LINE_ENERGY_KEV",
    "FRAMES",
]

#: Effective energy (keV) of the ``line`` level: the energy of ``MU_WATER_60KEV_PER_MM``.
LINE_ENERGY_KEV = 60.0

#: Frames a tool's pose maps into: the CT's LPS frame or the camera frame.
FRAMES = ("lps", "camera")

#: After a hit the next intersection search starts this far (mm) along the ray.
SKIP_MM = 1e-3

#: Most surface crossings followed per ray (a guard; a plate with six holes seen edge-on
#: has fewer than 30).
MAX_HITS = 256

#: Vertices closer than this (mm) are merged when a mesh is cleaned.
MERGE_MM = 1e-4


class DistractorError(InputError):
    """A tool, its size, material, pose or mesh cannot be used; the message names it."""


# ------------------------------------------------------------------------------- checks


def _positive(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise DistractorError(f"{name}: expected a number of mm, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise DistractorError(f"{name}: must be a positive number of mm, got {value!r}")
    return v


def _material(material: str, density_g_cm3) -> tuple[str, float]:
    if material not in MATERIALS:
        raise DistractorError(f"material {material!r}: not one of {', '.join(MATERIALS)}")
    rho = nominal_density(material) if density_g_cm3 is None else density_g_cm3
    if isinstance(rho, bool) or not isinstance(rho, (int, float, np.integer, np.floating)) \
            or not (math.isfinite(float(rho)) and float(rho) > 0):
        raise DistractorError(f"density_g_cm3 of {material}: must be a positive number of g/cm^3, got {rho!r}")
    return material, float(rho)


def _sides(sides) -> int:
    if isinstance(sides, bool) or not isinstance(sides, (int, np.integer)) or not 3 <= sides <= 512:
        raise DistractorError(f"sides: must be an integer in [3, 512] (polygon sides of a round part), got {sides!r}")
    return int(sides)


# ------------------------------------------------------------------------------- meshes


@dataclass(frozen=True, eq=False)
class ToolMesh:
    """A closed, outward-oriented triangle mesh of one material, in the tool's frame (mm).

    Attributes:
        kind: what it is (``"screw"``, ``"k_wire"``, ...).
        material: a name of :data:`sim.physics.materials.MATERIALS`.
        density_g_cm3: its density.
        vertices: ``(N, 3)`` float64 mm.
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise seen from outside.
    """

    kind: str
    material: str
    density_g_cm3: float
    vertices: np.ndarray
    faces: np.ndarray

    @property
    def volume_mm3(self) -> float:
        """Enclosed volume (mm^3), positive for an outward-oriented closed mesh."""
        v = self.vertices[self.faces]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)

    @classmethod
    def from_arrays(cls, vertices, faces, material: str, density_g_cm3: float | None = None,
                    kind: str = "mesh") -> ToolMesh:
        """A tool from any closed mesh ``(N, 3)`` mm / ``(F, 3)``; cleaned and checked by :func:`clean_mesh`."""
        material, rho = _material(material, density_g_cm3)
        try:
            v = np.asarray(vertices, np.float64)
            f = np.asarray(faces, np.int64)
        except (TypeError, ValueError) as e:
            raise DistractorError(f"{kind} mesh: vertices and faces must be numeric arrays ({e})") from None
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise DistractorError(f"{kind} mesh: expected vertices (N, 3) and faces (F, 3), "
                                  f"got {v.shape} and {f.shape}")
        if not np.all(np.isfinite(v)) or f.min() < 0 or f.max() >= len(v):
            raise DistractorError(f"{kind} mesh: vertices must be finite and faces index them")
        v, f = clean_mesh(v, f, what=f"{kind} mesh")
        return cls(kind, material, rho, v, f)


def topology(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """pymeshlab's topological measures of a mesh (``boundary_edges``, ``non_two_manifold_edges``, ...)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32)))
    return dict(ms.get_topological_measures())


def _directed_edges_paired(faces: np.ndarray) -> bool:
    """Every directed edge occurs once and its reverse once: closed, manifold, coherently oriented."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    n = int(faces.max()) + 1
    key = e[:, 0] * n + e[:, 1]
    if len(np.unique(key)) != len(key):
        return False
    return bool(np.all(np.isin(e[:, 1] * n + e[:, 0], key)))


def clean_mesh(vertices, faces, *, what: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Clean a mesh with pymeshlab and check that it bounds a solid.

    Merges vertices closer than :data:`MERGE_MM`, removes duplicate vertices and faces,
    zero-area faces and unreferenced vertices; then requires pymeshlab's topological measures
    to show no boundary edge and no non-manifold edge or vertex, every directed edge to pair
    with its reverse (consistent orientation) and a positive enclosed volume (outward normals).
    Returns ``(vertices (N, 3) float64, faces (F, 3) int64)``; raises :class:`DistractorError`
    naming ``what`` and the failed check.
    """
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32)))
    ms.meshing_merge_close_vertices(threshold=ml.PureValue(MERGE_MM))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    v = np.array(m.vertex_matrix(), np.float64)
    f = np.array(m.face_matrix(), np.int64)
    if len(f) == 0:
        raise DistractorError(f"{what}: no faces left after cleaning")
    topo = ms.get_topological_measures()
    bad = {k: topo[k] for k in ("boundary_edges", "non_two_manifold_edges", "non_two_manifold_vertices") if topo[k]}
    if bad:
        raise DistractorError(f"{what}: not a closed manifold surface after cleaning "
                              f"({', '.join(f'{k}={n}' for k, n in bad.items())})")
    if not _directed_edges_paired(f):
        raise DistractorError(f"{what}: faces are not coherently oriented "
                              "(a directed edge does not pair with its reverse)")
    vol = ToolMesh("", "", 1.0, v, f).volume_mm3
    if not vol > 0:
        raise DistractorError(f"{what}: encloses a volume of {vol:g} mm^3; faces must point outward")
    return v, f


def _as_ml(vertices, faces):
    import pymeshlab as ml

    return ml.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32))


def _arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    return np.array(mesh.vertex_matrix(), np.float64), np.array(mesh.face_matrix(), np.int64)


def _frustum(r0: float, r1: float, z0: float, z1: float, sides: int):
    """pymeshlab cone/cylinder about z from ``z0`` (radius ``r0``) to ``z1`` (``r1``); vertices
    on the circles (an inscribed polygon)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.create_cone(r0=r0, r1=r1, h=z1 - z0, subdiv=sides)  # about y, r0 at y = -h/2
    v, f = _arrays(ms.current_mesh())
    v = np.c_[v[:, 0], -v[:, 2], v[:, 1]] + [0.0, 0.0, 0.5 * (z0 + z1)]  # y -> z, a proper rotation
    return v, f


def _box(size, center=(0.0, 0.0, 0.0)):
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.create_cube(size=1.0)
    v, f = _arrays(ms.current_mesh())
    return v * np.asarray(size, np.float64) + np.asarray(center, np.float64), f


def _boolean(op: str, first, others):
    """Union or difference (pymeshlab, exact libigl booleans) of meshes given as (V, F)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(_as_ml(*first))
    current = 0
    for other in others:
        ms.add_mesh(_as_ml(*other))
        getattr(ms, f"generate_boolean_{op}")(first_mesh=current, second_mesh=ms.current_mesh_id())
        current = ms.current_mesh_id()
    return _arrays(ms.current_mesh())


def _tool(kind: str, v, f, material: str, density) -> ToolMesh:
    material, rho = _material(material, density)
    v, f = clean_mesh(v, f, what=kind)
    return ToolMesh(kind, material, rho, v, f)


def screw(length_mm: float = 40.0, diameter_mm: float = 6.5, *, head_diameter_mm: float | None = None,
          head_height_mm: float | None = None, tip_mm: float | None = None, material: str = "titanium",
          density_g_cm3: float | None = None, sides: int = 32) -> ToolMesh:
    """A bone screw: conical tip (apex at the origin, ``tip_mm`` long, default the radius), a
    shaft of ``diameter_mm`` to ``z = length_mm`` and a head (default 1.8 x diameter wide, 0.6 x
    diameter high) above it; threads are not modelled (their mean diameter is the shaft's)."""
    length = _positive(length_mm, "screw length_mm")
    d = _positive(diameter_mm, "screw diameter_mm")
    hd = _positive(1.8 * d if head_diameter_mm is None else head_diameter_mm, "screw head_diameter_mm")
    hh = _positive(0.6 * d if head_height_mm is None else head_height_mm, "screw head_height_mm")
    tip = _positive(0.5 * d if tip_mm is None else tip_mm, "screw tip_mm")
    if tip >= length:
        raise DistractorError(f"screw tip_mm: must be shorter than length_mm ({length:g}), got {tip:g}")
    if hd <= d:
        raise DistractorError(f"screw head_diameter_mm: must exceed diameter_mm ({d:g}), got {hd:g}")
    n = _sides(sides)
    # the parts overlap (the cone's rim inside the shaft, the shaft into the head): a union of
    # coincident faces or rims is not a manifold for every size
    v, f = _boolean("union", _frustum(0.0, 0.97 * d / 2, 0.0, tip, n),
                    [_frustum(d / 2, d / 2, 0.6 * tip, length, n),
                     _frustum(hd / 2, hd / 2, length - 0.1 * hh, length + hh, n)])
    return _tool("screw", v, f, material, density_g_cm3)


def k_wire(length_mm: float = 150.0, diameter_mm: float = 2.0, *, material: str = "stainless_steel",
           density_g_cm3: float | None = None, sides: int = 24) -> ToolMesh:
    """A Kirschner wire: a closed cylinder about z from 0 to ``length_mm`` (usual diameters
    1.6-2.5 mm), its cross section the ``sides``-gon inscribed in the circle."""
    length = _positive(length_mm, "k_wire length_mm")
    d = _positive(diameter_mm, "k_wire diameter_mm")
    v, f = _frustum(d / 2, d / 2, 0.0, length, _sides(sides))
    return _tool("k_wire", v, f, material, density_g_cm3)


def plate(length_mm: float = 80.0, width_mm: float = 12.0, thickness_mm: float = 3.0, *, holes: int = 6,
          hole_diameter_mm: float = 4.5, material: str = "titanium", density_g_cm3: float | None = None,
          sides: int = 24) -> ToolMesh:
    """A bone plate: a box (x length, y width, z thickness) centred at the origin with ``holes``
    round holes through z, evenly spaced along x (pymeshlab boolean difference)."""
    length = _positive(length_mm, "plate length_mm")
    width = _positive(width_mm, "plate width_mm")
    thick = _positive(thickness_mm, "plate thickness_mm")
    if isinstance(holes, bool) or not isinstance(holes, (int, np.integer)) or holes < 0:
        raise DistractorError(f"plate holes: must be an integer >= 0, got {holes!r}")
    body = _box((length, width, thick))
    if holes:
        hd = _positive(hole_diameter_mm, "plate hole_diameter_mm")
        pitch = length / holes
        if hd >= min(width, pitch):
            raise DistractorError(f"plate hole_diameter_mm: must be below the width ({width:g}) and the hole pitch "
                                  f"({pitch:g}), got {hd:g}")
        n = _sides(sides)
        cyl = _frustum(hd / 2, hd / 2, -thick, thick, n)
        drills = [(cyl[0] + [(-length / 2 + (k + 0.5) * pitch), 0.0, 0.0], cyl[1]) for k in range(holes)]
        body = _boolean("difference", body, drills)
    return _tool("plate", *body, material, density_g_cm3)


def retractor(blade_length_mm: float = 60.0, handle_length_mm: float = 120.0, width_mm: float = 25.0,
              thickness_mm: float = 1.5, *, bend_deg: float = 90.0, material: str = "stainless_steel",
              density_g_cm3: float | None = None) -> ToolMesh:
    """A hand-held retractor: a flat handle along -x (``handle_length_mm``) and a blade
    (``blade_length_mm``) bent by ``bend_deg`` about the y axis at the origin (toward -z), both
    ``width_mm`` wide (y) and ``thickness_mm`` thick (pymeshlab boolean union)."""
    blade = _positive(blade_length_mm, "retractor blade_length_mm")
    handle = _positive(handle_length_mm, "retractor handle_length_mm")
    width = _positive(width_mm, "retractor width_mm")
    thick = _positive(thickness_mm, "retractor thickness_mm")
    if isinstance(bend_deg, bool) or not isinstance(bend_deg, (int, float, np.integer, np.floating)) \
            or not 0 <= float(bend_deg) <= 135:
        raise DistractorError(f"retractor bend_deg: must be a number of degrees in [0, 135], got {bend_deg!r}")
    hv, hf = _box((handle + thick / 2, width, thick), (-(handle - thick / 2) / 2, 0.0, 0.0))
    bv, bf = _box((blade + thick / 2, width, thick), ((blade - thick / 2) / 2, 0.0, 0.0))
    a = math.radians(float(bend_deg))
    rot = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    v, f = _boolean("union", (hv, hf), [(bv @ rot.T, bf)])
    return _tool("retractor", v, f, material, density_g_cm3)


def table(width_mm: float = 500.0, length_mm: float = 2000.0, thickness_mm: float = 25.0, *,
          material: str = "carbon", density_g_cm3: float | None = 0.2) -> ToolMesh:
    """An operating-table top: a slab (x width, y length, z thickness) centred at the origin.
    The default is a carbon-fibre sandwich homogenised to 0.2 g/cm^3 (25 mm of it attenuates
    like about 1.2 mm of aluminium at 60 keV); pose it with ``frame="camera"`` (fixed to the
    C-arm) or ``"lps"`` (under the patient)."""
    size = (_positive(width_mm, "table width_mm"), _positive(length_mm, "table length_mm"),
            _positive(thickness_mm, "table thickness_mm"))
    return _tool("table", *_box(size), material, density_g_cm3)


def _tube(path: np.ndarray, r_out: float, r_in: float, sides: int):
    """A tube of radius ``r_out`` swept along ``path`` ``(N, 3)`` with parallel-transport frames,
    hollow (annular caps) when ``r_in > 0``; outward-oriented."""
    seg = np.diff(path, axis=0)
    tang = np.empty_like(path)
    tang[0], tang[-1] = seg[0], seg[-1]
    tang[1:-1] = seg[1:] / np.linalg.norm(seg[1:], axis=1, keepdims=True) + seg[:-1] / np.linalg.norm(
        seg[:-1], axis=1, keepdims=True)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    helper = np.eye(3)[int(np.argmin(np.abs(tang[0])))]
    normal = np.empty_like(path)
    normal[0] = np.cross(tang[0], helper)
    normal[0] /= np.linalg.norm(normal[0])
    for i in range(1, len(path)):
        nv = normal[i - 1] - np.dot(normal[i - 1], tang[i]) * tang[i]
        normal[i] = nv / np.linalg.norm(nv)
    binormal = np.cross(tang, normal)
    theta = 2 * np.pi * np.arange(sides) / sides
    dirs = np.cos(theta)[None, :, None] * normal[:, None] + np.sin(theta)[None, :, None] * binormal[:, None]
    n, k = len(path), np.arange(sides)
    k1 = (k + 1) % sides

    def wall(base, outward):
        faces = []
        for i in range(n - 1):
            a, b = base + i * sides + k, base + i * sides + k1
            c, d = base + (i + 1) * sides + k1, base + (i + 1) * sides + k
            tri = [np.c_[a, b, c], np.c_[a, c, d]]
            faces += tri if outward else [t[:, ::-1] for t in tri]
        return faces

    outer = (path[:, None] + r_out * dirs).reshape(-1, 3)
    faces = wall(0, True)
    if r_in > 0:
        inner = (path[:, None] + r_in * dirs).reshape(-1, 3)
        verts = np.concatenate([outer, inner])
        m = n * sides
        faces += wall(m, False)
        for i, sign in ((0, -1), (n - 1, 1)):  # annular caps: -T at the start, +T at the end
            o, o1, q, q1 = i * sides + k, i * sides + k1, m + i * sides + k, m + i * sides + k1
            tri = [np.c_[q, o1, o], np.c_[q, q1, o1]]
            faces += tri if sign < 0 else [t[:, ::-1] for t in tri]
    else:
        verts = np.concatenate([outer, path[[0, -1]]])
        c0, c1 = n * sides, n * sides + 1
        faces += [np.c_[np.full(sides, c0), k1, k], np.c_[np.full(sides, c1), (n - 1) * sides + k,
                                                             (n - 1) * sides + k1]]
    return verts, np.concatenate(faces).astype(np.int64)


def cable(path_mm, *, core_diameter_mm: float = 1.5, outer_diameter_mm: float = 4.0, sides: int = 16,
          core_material: str = "copper", sheath_material: str = "pvc") -> tuple[ToolMesh, ToolMesh]:
    """A cable along ``path_mm`` ``(N, 3)`` (N >= 2, mm, in the frame the pose maps from): a solid
    copper core and a hollow PVC sheath around it, two meshes to pose alike (the same pose)."""
    try:
        p = np.asarray(path_mm, np.float64)
    except (TypeError, ValueError):
        raise DistractorError("cable path_mm: expected (N, 3) points in mm") from None
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2 or not np.all(np.isfinite(p)):
        raise DistractorError(f"cable path_mm: expected (N, 3) finite points in mm with N >= 2, got shape {p.shape}")
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    rc = _positive(core_diameter_mm, "cable core_diameter_mm") / 2
    ro = _positive(outer_diameter_mm, "cable outer_diameter_mm") / 2
    if ro <= rc:
        raise DistractorError(f"cable outer_diameter_mm: must exceed core_diameter_mm ({2 * rc:g}), got {2 * ro:g}")
    if seg.min() <= 2 * ro:
        raise DistractorError(f"cable path_mm: consecutive points must be more than the outer diameter ({2 * ro:g} mm) "
                              f"apart, got {seg.min():g} mm")
    n = _sides(sides)
    core = _tool("cable_core", *_tube(p, rc, 0.0, n), core_material, None)
    sheath = _tool("cable_sheath", *_tube(p, ro, rc, n), sheath_material, None)
    return core, sheath


# ------------------------------------------------------------------------------- placement


def _check_pose(pose, what: str) -> np.ndarray:
    try:
        p = np.asarray(pose, np.float64)
    except (TypeError, ValueError):
        raise DistractorError(f"{what}: expected a (4, 4) rigid transform") from None
    if p.shape != (4, 4) or not np.all(np.isfinite(p)):
        raise DistractorError(f"{what}: expected a finite (4, 4) rigid transform, got shape {p.shape}")
    r = p[:3, :3]
    err = np.abs(r.T @ r - np.eye(3)).max()
    if err > 1e-6 or np.linalg.det(r) < 0 or np.abs(p[3] - (0, 0, 0, 1)).max() > 1e-12:
        raise DistractorError(f"{what}: must be a rigid transform (orthonormal rotation, last row 0 0 0 1); "
                              f"rotation error {err:.2e}")
    return p


@dataclass(frozen=True, eq=False)
class Distractor:
    """A tool placed in the field.

    Attributes:
        mesh: the :class:`ToolMesh`.
        pose: ``(4, 4)`` rigid map from the tool's frame (mm) to ``frame`` (mm).
        frame: ``"lps"`` (the CT's patient frame: the tool moves with the anatomy's pose) or
            ``"camera"`` (the C-arm's camera frame: the same in every view).
    """

    mesh: ToolMesh
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    frame: str = "lps"

    def __post_init__(self) -> None:
        if not isinstance(self.mesh, ToolMesh):
            raise DistractorError(f"distractor mesh: expected a ToolMesh, got {type(self.mesh).__name__}")
        if self.frame not in FRAMES:
            raise DistractorError(f"distractor frame: must be one of {FRAMES}, got {self.frame!r}")
        object.__setattr__(self, "pose", _check_pose(self.pose, f"{self.mesh.kind} pose"))

    def vertices(self) -> np.ndarray:
        """``(N, 3)`` vertices in ``frame`` (mm)."""
        return self.mesh.vertices @ self.pose[:3, :3].T + self.pose[:3, 3]


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation ``(3, 3)`` (a normalised Gaussian quaternion)."""
    q = rng.standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


#: The tool kinds :func:`random_tools` draws from (a table and a cable are drawn separately).
RANDOM_TOOL_KINDS = ("screw", "k_wire", "plate", "retractor")


def _random_tool_mesh(rng: np.random.Generator) -> ToolMesh:
    """One tool of :data:`RANDOM_TOOL_KINDS`, of a random kind and random sizes (mm; the ranges of
    :func:`random_tools`)."""
    kind = RANDOM_TOOL_KINDS[int(rng.integers(len(RANDOM_TOOL_KINDS)))]
    if kind == "screw":
        return screw(rng.uniform(25, 80), rng.uniform(4.5, 7.5))
    if kind == "k_wire":
        return k_wire(rng.uniform(80, 200), rng.uniform(1.6, 2.5), sides=12)
    if kind == "plate":
        return plate(rng.uniform(40, 140), rng.uniform(10, 16), rng.uniform(2.0, 4.0),
                     holes=int(rng.integers(2, 11)), hole_diameter_mm=4.0, sides=12)
    return retractor(rng.uniform(40, 80), rng.uniform(80, 160), rng.uniform(20, 40), rng.uniform(1.0, 2.5),
                     bend_deg=rng.uniform(45, 110))


def implanted_tools(rng: np.random.Generator, center_lps, *, tools: tuple[int, int] = (2, 5),
                    spread_mm: tuple[float, float, float] = (80.0, 50.0, 70.0)) -> list[Distractor]:
    """Metal tools fixed to the patient around the anatomy, as in a frame of instrumented surgery.

    ``tools`` (``(low, high)``, inclusive) screws, K-wires, plates and retractors of the sizes of
    :func:`random_tools`, each at a uniformly random orientation with its centre uniform in the
    box ``center_lps +- spread_mm`` (LPS mm: left-right, anterior-posterior, inferior-superior),
    in the patient frame (``frame="lps"``): unlike :func:`random_tools`' camera-fixed ones they
    move with the anatomy from view to view, as a screw in the bone or a retractor in the wound
    does, so a registration cannot tell them from anatomy by their place in the image.

    >>> import numpy as np
    >>> tools = implanted_tools(np.random.default_rng(0), [0.0, 0.0, 0.0], tools=(3, 3))
    >>> len(tools), {t.frame for t in tools}
    (3, {'lps'})
    """
    if not isinstance(rng, np.random.Generator):
        raise DistractorError(f"implanted_tools needs a numpy Generator, got {type(rng).__name__}")
    lo, hi = (int(v) for v in tools)
    if not 0 <= lo <= hi:
        raise DistractorError(f"implanted_tools: tools must be (low, high) with 0 <= low <= high, got {tools!r}")
    center = np.asarray(center_lps, dtype=np.float64).reshape(3)
    spread = np.asarray(spread_mm, dtype=np.float64).reshape(3)
    if not (np.isfinite(center).all() and np.isfinite(spread).all() and (spread >= 0).all()):
        raise DistractorError(f"implanted_tools: center_lps and spread_mm must be finite (spread >= 0), got "
                              f"{center.tolist()} and {spread.tolist()}")
    out = []
    for _ in range(int(rng.integers(lo, hi + 1))):
        mesh = _random_tool_mesh(rng)
        pose = np.eye(4)
        pose[:3, :3] = _random_rotation(rng)
        pose[:3, 3] = center + rng.uniform(-1.0, 1.0, 3) * spread
        out.append(Distractor(mesh, pose, frame="lps"))
    return out


def random_tools(rng: np.random.Generator, geometry, *, tools: tuple[int, int] = (1, 4),
                 table_probability: float = 0.5, cable_probability: float = 0.3) -> list[Distractor]:
    """A random arrangement of tools in the field of view of ``geometry``, in the camera frame.

    For training images a tool's appearance is what matters, not its anatomical plausibility:
    ``tools`` (``(low, high)``, inclusive) screws, K-wires, plates and retractors of random
    sizes, each at a uniformly random orientation with its centre at a depth of ``SOD +- 80``
    mm and anywhere in the view cone at that depth (so it may be cut by the field's edge);
    with ``table_probability`` a carbon table top 60-120 mm nearer the detector than the
    isocentre, and with ``cable_probability`` a cable crossing the view. Sizes (mm): screws
    25-80 long, 4.5-7.5 wide; K-wires 80-200 long, 1.6-2.5 wide; plates 40-140 long with 2-10
    holes; retractors 20-40 wide with blades of 40-80. Returns :class:`Distractor` s with
    ``frame="camera"``: the same image whatever the volume pose.
    """
    if not (isinstance(rng, np.random.Generator)):
        raise DistractorError(f"random_tools needs a numpy Generator, got {type(rng).__name__}")
    lo, hi = (int(v) for v in tools)
    if not 0 <= lo <= hi:
        raise DistractorError(f"random_tools: tools must be (low, high) with 0 <= low <= high, got {tools!r}")
    g = geometry
    half = 0.5 * np.array([g.width, g.height]) * g.pixel_spacing_mm  # detector half extent (mm)
    out = []

    def place(depth_mm: float, rot: np.ndarray) -> np.ndarray:
        pose = np.eye(4)
        pose[:3, :3] = rot
        xy = rng.uniform(-1.0, 1.0, 2) * half * depth_mm / g.sdd_mm
        pose[:3, 3] = [xy[0], xy[1], depth_mm]
        return pose

    for _ in range(int(rng.integers(lo, hi + 1))):
        mesh = _random_tool_mesh(rng)
        out.append(Distractor(mesh, place(g.sod_mm + rng.uniform(-80, 80), _random_rotation(rng)), frame="camera"))
    if rng.random() < table_probability:
        a = np.radians(rng.uniform(-20, 20))  # table top tilted a little against the detector plane
        rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        pose = np.eye(4)
        pose[:3, :3] = rot
        pose[:3, 3] = [0.0, 0.0, g.sod_mm + rng.uniform(60, 120)]
        out.append(Distractor(table(), pose, frame="camera"))
    if rng.random() < cable_probability:
        depth = g.sod_mm + rng.uniform(-60, 150)
        reach = 1.5 * half * depth / g.sdd_mm
        ends = rng.uniform(-1, 1, (2, 2)) * reach
        ends[1] = -ends[0] + rng.normal(0, 0.3, 2) * reach  # across the view
        if np.linalg.norm(ends[1] - ends[0]) < 0.5 * reach.min():
            ends[1] = ends[0] + [reach[0], 0.0]
        t = np.linspace(0, 1, 8)[:, None]
        along = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
        sag = np.sin(np.pi * t) * rng.normal(0, 0.2) * reach.mean() * np.array([-along[1], along[0]])
        path = np.concatenate([ends[0] + t * (ends[1] - ends[0]) + sag, np.full((8, 1), depth)], axis=1)
        for part in cable(path, sides=8):
            out.append(Distractor(part, np.eye(4), frame="camera"))
    return out


def _mitsuba_mesh(name: str, vertices: np.ndarray, faces: np.ndarray):
    import mitsuba as mi

    mesh = mi.Mesh(name, len(vertices), len(faces), has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(vertices, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(faces, np.uint32).ravel())
    params.update()
    return mesh


class DistractorField:
    """Tools in the field of one C-arm view geometry: per-pixel chords and their attenuation.

    Args:
        tools: :class:`Distractor` s (any number, any frames).
        geometry: the :class:`sim.projection.geometry.CArmGeometry` of the images (e.g. a renderer's
            ``geometry``).
        center_lps: ``(3,)`` anatomy centre c (LPS mm) of the poses, as the renderer's.
        scene: the scene the renderer loaded (its Mitsuba sensor makes the rays).

    Channels: one per distinct (material, density) of the tools, in the order of first
    appearance (:attr:`channels`); :meth:`chords` gives ``(B, C, H, W)`` mm for poses
    ``(B, 4, 4)``, traced in one symbolic loop per channel and frame (see the module doc).
    """

    def __init__(self, tools: Sequence[Distractor], geometry, center_lps, *, scene: str | None = None):
        tools = tuple(tools)
        for t in tools:
            if not isinstance(t, Distractor):
                raise DistractorError(f"tools: expected Distractor objects, got {type(t).__name__}")
        if not isinstance(geometry, CArmGeometry):
            raise DistractorError(f"geometry: expected a CArmGeometry, got {type(geometry).__name__}")
        c = np.asarray(center_lps, np.float64).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise DistractorError(f"center_lps: expected 3 finite LPS mm values, got {center_lps}")
        self.tools = tools
        self.geometry = geometry
        self.center_lps = c
        self.scene_name = scene or DEFAULT_SCENE
        channels: list[tuple[str, float]] = []
        for t in tools:
            key = (t.mesh.material, t.mesh.density_g_cm3)
            if key not in channels:
                channels.append(key)
        #: ``((material, density g/cm^3), ...)``: the channels of :meth:`chords`.
        self.channels: tuple[tuple[str, float], ...] = tuple(channels)
        #: Rays of the last :meth:`chords` call with an unpaired entry or exit (see the module doc).
        self.unpaired_rays = 0
        self._scenes: dict | None = None
        self._sensor_scene = None

    # ------------------------------------------------------------ mitsuba
    def _setup(self) -> None:
        if self._scenes is not None:
            return
        import mitsuba as mi

        self._sensor_scene = load_mitsuba_scene(load_scene(self.scene_name), self.geometry)
        self._sensor = self._sensor_scene.sensors()[0]
        self._integrator = self._sensor_scene.integrator()
        self._camera_from_world = camera_from_sensor(self._sensor)  # the renderer's own map
        scenes = {}
        for frame in FRAMES:
            for ci, key in enumerate(self.channels):
                members = [t for t in self.tools if t.frame == frame and (t.mesh.material, t.mesh.density_g_cm3) == key]
                if members:
                    shapes = {f"tool{k}": _mitsuba_mesh(f"tool{k}", t.vertices(), t.mesh.faces)
                              for k, t in enumerate(members)}
                    scenes[(frame, ci)] = mi.load_dict({"type": "scene", **shapes})
        self._scenes = scenes

    def _rays(self, frame_from_world: np.ndarray):
        """The renderer's pixel-centre rays, mapped by ``(B, 4, 4)`` rigid maps from Mitsuba's
        world frame: the ``ctxreg_drr`` integrator's own ray generation."""
        h, w = self.geometry.height, self.geometry.width
        self._integrator.set_world_to_index(frame_from_world)
        return self._integrator.rays_in_index_space(self._sensor, w, h, len(frame_from_world) * h * w)

    @staticmethod
    def _trace(scene, o, d):
        """Length (mm) inside the closed meshes of ``scene`` along each ray, and an unpaired flag."""
        import drjit as dr
        import mitsuba as mi

        n_rays = dr.width(o)
        active = dr.full(mi.Bool, True, n_rays)
        t0 = dr.zeros(mi.Float, n_rays)
        acc = dr.zeros(mi.Float, n_rays)
        depth = dr.zeros(mi.Int32, n_rays)
        t_last = dr.zeros(mi.Float, n_rays)
        dropped = dr.full(mi.Bool, False, n_rays)
        hits = dr.zeros(mi.UInt32, n_rays)
        skip = dr.opaque(mi.Float, SKIP_MM)
        max_hits = dr.opaque(mi.UInt32, MAX_HITS)

        def cond(active, t0, acc, depth, t_last, dropped, hits):
            return active

        def body(active, t0, acc, depth, t_last, dropped, hits):
            si = scene.ray_intersect(mi.Ray3f(o + d * t0, d), mi.RayFlags.Minimal, False, active)
            hit = active & si.is_valid()
            t = t0 + si.t
            entering = dr.dot(si.n, d) < 0
            stray = hit & ~entering & (depth <= 0)  # an exit with nothing open: dropped
            count = hit & ~stray
            acc = dr.select(count, acc + dr.select(entering, -t, t), acc)
            depth = dr.select(count, depth + dr.select(entering, 1, -1), depth)
            t_last = dr.select(hit, t, t_last)
            dropped = dropped | stray
            t0 = dr.select(hit, t + skip, t0)
            hits = hits + 1
            return hit & (hits < max_hits), t0, acc, depth, t_last, dropped, hits

        state = dr.while_loop(state=(active, t0, acc, depth, t_last, dropped, hits), cond=cond, body=body,
                              label="ctxreg_distractor_chords")
        _, _, acc, depth, t_last, dropped, _ = state
        acc = acc + mi.Float(depth) * t_last  # entries left open close at the last hit
        unpaired = dropped | (depth != 0)
        return np.array(acc, np.float64), np.array(unpaired, bool)

    # ------------------------------------------------------------ public
    def chords(self, poses) -> np.ndarray:
        """Path lengths (mm) inside the tools, per channel: ``(B, C, H, W)`` float32 for poses
        ``(4, 4)`` or ``(B, 4, 4)`` (volume poses T, as the renderer's; ``B = 1`` for one)."""

        poses = DRRRenderer._check_poses(poses)
        b, h, w = len(poses), self.geometry.height, self.geometry.width
        out = np.zeros((b, len(self.channels), h, w), np.float32)
        self.unpaired_rays = 0
        if not self.tools:
            return out
        self._setup()
        per_launch = max(1, MAX_RAYS_PER_LAUNCH // (h * w))
        unpaired = 0
        for start in range(0, b, per_launch):
            out[start:start + per_launch], odd = self._chords(poses[start:start + per_launch])
            unpaired += odd
        self.unpaired_rays = unpaired
        return out

    def _chords(self, poses: np.ndarray) -> tuple[np.ndarray, int]:
        b, h, w = len(poses), self.geometry.height, self.geometry.width
        out = np.zeros((b, len(self.channels), h, w), np.float32)
        rays = {}
        if any(f == "lps" for f, _ in self._scenes):
            lps_from_world = np.linalg.inv(extrinsic_lps_to_camera(poses, self.center_lps)) @ self._camera_from_world
            rays["lps"] = self._rays(lps_from_world)
        if any(f == "camera" for f, _ in self._scenes):
            rays["camera"] = self._rays(self._camera_from_world[None])
        unpaired = np.zeros((b, h, w), bool)
        for (frame, ci), scene in self._scenes.items():
            length, odd = self._trace(scene, *rays[frame])
            nb = b if frame == "lps" else 1
            out[:, ci] += length.reshape(nb, h, w).astype(np.float32)
            unpaired |= odd.reshape(nb, h, w)
        return out, int(unpaired.sum())

    def line_integral(self, poses) -> np.ndarray:
        """``(B, H, W)``: the tools' ``sum_c mu_c(60 keV) chord_c`` (dimensionless)."""
        chords = self.chords(poses)
        return add_to_line_integral(np.zeros((chords.shape[0],) + chords.shape[2:], np.float32), chords, self.channels)

    def materials(self, names: Sequence[str] = ()) -> tuple[str, ...]:
        """``names`` followed by the tools' materials that are not among them."""
        out = list(names)
        for m, _ in self.channels:
            if m not in out:
                out.append(m)
        return tuple(out)


# ------------------------------------------------------------------------------- attenuation


def mu_line(material: str, density_g_cm3: float) -> float:
    """Linear attenuation (1/mm) of a tool material at the line level's :data:`LINE_ENERGY_KEV`."""
    material, rho = _material(material, density_g_cm3)
    return float(mu_linear(material, LINE_ENERGY_KEV, rho))


def _check_chords(chords, channels, batch_shape=None) -> np.ndarray:
    c = np.asarray(chords)
    if c.ndim != 4 or c.shape[1] != len(channels):
        raise DistractorError(f"chords: expected (B, C={len(channels)}, H, W) mm, got shape {c.shape}")
    if batch_shape is not None and (c.shape[0], *c.shape[2:]) != tuple(batch_shape):
        raise DistractorError(f"chords {c.shape} do not match the images {tuple(batch_shape)}")
    return c


def add_to_line_integral(line, chords, channels) -> np.ndarray:
    """``line + sum_c mu_c chord_c``: line integrals ``(B, H, W)`` with the tools, float32.

    ``chords`` ``(B, C, H, W)`` mm and ``channels`` ``((material, density), ...)`` as
    :meth:`DistractorField.chords` / :attr:`DistractorField.channels`; ``mu_c`` at
    :data:`LINE_ENERGY_KEV` (:func:`mu_line`)."""
    line = np.asarray(line)
    c = _check_chords(chords, channels, line.shape)
    out = line.astype(np.float64)
    for k, (m, rho) in enumerate(channels):
        out += mu_line(m, rho) * c[:, k]
    return out.astype(np.float32)


def add_to_density_integrals(L, names: Sequence[str], chords, channels) -> tuple[np.ndarray, tuple[str, ...]]:
    """Density line integrals with the tools: ``(L', names')``.

    ``L`` ``(B, M, H, W)`` g/cm^2 over materials ``names``; each channel adds
    ``density * chord / 10`` (g/cm^3 x mm -> g/cm^2) to its material's channel, appended to
    ``names`` (and as a new channel of ``L``) when missing. ``L'`` is float32
    ``(B, M', H, W)``."""
    L = np.asarray(L)
    names = tuple(names)
    if L.ndim != 4 or L.shape[1] != len(names):
        raise DistractorError(f"density integrals: expected (B, M={len(names)}, H, W) g/cm^2, got shape {L.shape}")
    c = _check_chords(chords, channels, (L.shape[0], *L.shape[2:]))
    out_names = list(names)
    for m, _ in channels:
        if m not in out_names:
            out_names.append(m)
    out = np.zeros((L.shape[0], len(out_names)) + L.shape[2:], np.float32)
    out[:, :len(names)] = L
    for k, (m, rho) in enumerate(channels):
        out[:, out_names.index(m)] += (rho / 10.0) * c[:, k]
    return out, tuple(out_names)


# ------------------------------------------------------------------------------- imaging


class RendererWithDistractors:
    """A :class:`sim.projection.drr.DRRRenderer` whose images include tools in the field.

    ``render(poses)`` is the renderer's, plus the tools: ``line-integral`` adds
    ``mu * chord``, ``intensity`` multiplies by ``exp(-mu * chord)``, ``density`` adds
    ``rho * chord / 10`` g/cm^2 with the tools' missing materials appended
    (:attr:`channel_names`). Everything else (``geometry``, ``center_lps``,
    ``projection_matrix``, ...) is the wrapped renderer's.
    """

    def __init__(self, renderer, tools: Sequence[Distractor]):
        self.renderer = renderer
        self.field = DistractorField(tools, renderer.geometry, renderer.center_lps, scene=renderer.settings.scene)
        q = renderer.settings.quantity
        self.channel_names = self.field.materials(renderer.channel_names) if q == "density" else renderer.channel_names

    def __getattr__(self, name):
        try:
            renderer = self.__dict__["renderer"]
        except KeyError:
            raise AttributeError(name) from None
        return getattr(renderer, name)

    def render(self, poses) -> np.ndarray:
        """As :meth:`sim.projection.drr.DRRRenderer.render`, with the tools."""
        poses = self.renderer._check_poses(poses)
        img = self.renderer.render(poses)
        if not self.field.tools:
            return img
        chords = self.field.chords(poses)
        q = self.renderer.settings.quantity
        if q == "density":
            return add_to_density_integrals(img, self.renderer.channel_names, chords, self.field.channels)[0]
        extra = add_to_line_integral(np.zeros_like(img), chords, self.field.channels)
        if q == "intensity":
            return (img * np.exp(-extra.astype(np.float64))).astype(np.float32)
        return (img + extra).astype(np.float32)


def imager_with_distractors(imager, tools: Sequence[Distractor]):
    """A copy of a :class:`sim.physics.imaging.XRayImager` (poly / full) whose images include the
    tools: its density renderer becomes a :class:`RendererWithDistractors` and its
    polychromatic model gains the tools' materials; spectrum, detector, noise, flat field and
    scatter (which sees the CT only) are shared. With no tools the imager itself is returned."""

    tools = tuple(tools)
    if not tools:
        return imager
    out = copy.copy(imager)
    out.renderer = RendererWithDistractors(imager.renderer, tools)
    out.model = Polychromatic(imager.spectrum, imager.detector, out.renderer.channel_names)
    return out
