"""``ctxreg evaluate`` and ``ctxreg register``: defaults (one dataclass each) and their runs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from register.cmaes import CMAESSettings
from sim.cli import CT_HELP
from sim.cliargs import opt
from sim.physics.options import level_field, physics_option

#: Monte Carlo histories per moving image with --physics full: a registration renders thousands
#: of images, and the smoothed scatter of 10^5 histories differs from that of 10^6 by a few %.
REGISTER_SCATTER_PHOTONS = 100_000

#: CMA-ES restarts of ``ctxreg register`` (IPOP, see :class:`register.cmaes.CMAESSettings`): a
#: user's X-ray is registered once, so spending up to 4x the time on a lost search is worth it.
REGISTER_RESTARTS = 3


@dataclass(frozen=True)
class EvaluateCommand:
    """Defaults of ``ctxreg evaluate``."""

    ct: str = field(metadata=opt(CT_HELP, group="input", metavar="PATH|phantom"))
    label_map: str | None = field(default=None, metadata=opt(
        "label map on the CT's grid: its centroid is the anatomy centre", group="input", metavar="PATH"))
    center: tuple[float, float, float] | None = field(default=None, metadata=opt(
        "anatomy centre c in LPS", group="input", unit="mm", nargs=3, metavar=("X", "Y", "Z")))
    cases: int = field(default=20, metadata=opt("number of target poses", group="protocol", metavar="N"))
    method: tuple[str, ...] = field(default=("cmaes",), metadata=opt(
        "registration methods to compare", group="protocol", nargs="+",
        choices=("cmaes", "contextual", "contextual+cmaes")))
    model: str | None = field(default=None, metadata=opt(
        "trained network checkpoint (ctxreg train) for the contextual methods", group="protocol",
        metavar="CKPT"))
    start: str = field(default="ap", metadata=opt(
        "start every case at AP, or near the truth (--local-rot / --local-trans)", group="protocol",
        choices=("ap", "local")))
    local_rot: float = field(default=5.0, metadata=opt(
        "largest start offset in rotation for --start local", group="protocol", unit="deg"))
    local_trans: float = field(default=10.0, metadata=opt(
        "largest start offset in translation for --start local", group="protocol", unit="mm"))
    seed: int = field(default=0, metadata=opt("seed of the target poses and starts", group="protocol"))
    size: tuple[int, int] = field(default=(128, 128), metadata=opt(
        "image rows and columns of targets and DRRs", group="protocol", unit="pixels", nargs=2,
        metavar=("H", "W")))
    scene: str = field(default="cios_fusion", metadata=opt("C-arm scene", group="protocol"))
    target_ray_model: str = field(default="siddon", metadata=opt(
        "ray model of the target images (the methods render with siddon): trilinear makes the "
        "targets differ from the DRRs", group="protocol", choices=("siddon", "trilinear")))
    target_physics: str = field(default="line", metadata=opt(
        "physics of the target images: line (DRRs like the methods') or poly (120 kVp spectrum, 7 "
        "materials, CsI detector, quantum noise: -log(I/I0)) or full (poly + Monte Carlo scatter, "
        "10^6 histories per target): a simulated domain gap", group="protocol", choices=("line", "poly", "full")))
    target_mas: float = field(default=2.5, metadata=opt(
        "exposure of poly and full targets (less mAs, more noise)", group="protocol", unit="mAs"))
    physics: str = level_field(group="protocol", help=(
        "physics of the methods' moving images: line (line-integral DRRs) or poly / full "
        "(noise-free -log(I/I0) at 120 kVp, full with 10^5 scatter histories per image)"))
    out: str = field(default="out/evaluate", metadata=opt(
        "folder for cases.csv, summary.json, table.md, violins.png", group="output", metavar="DIR"))


def run_evaluate(cmd: EvaluateCommand) -> list[Path]:
    from dataclasses import asdict

    from register.evaluate import METHODS, EvaluationError, EvaluationSettings, evaluate
    from sim.anatomy import anatomy_center
    from sim.ct_io import load_ct_spec
    from sim.physics.imaging import LogImageRenderer, PhysicsSettings
    from sim.render import DRRRenderer, RenderSettings

    settings = EvaluationSettings(cases=cmd.cases, seed=cmd.seed, size=tuple(cmd.size), start=cmd.start,
                                  local_rot_deg=cmd.local_rot, local_trans_mm=cmd.local_trans)
    volume = load_ct_spec(cmd.ct, label_map=cmd.label_map)
    center = np.asarray(cmd.center, float) if cmd.center is not None else anatomy_center(volume)
    if cmd.target_physics == "line" and cmd.target_mas != 2.5:
        raise EvaluationError("--target-mas only applies with --target-physics poly or full")
    if cmd.target_physics in ("poly", "full"):
        physics = PhysicsSettings(level=cmd.target_physics, mas=cmd.target_mas, seed=cmd.seed)
        target_renderer = LogImageRenderer(volume, physics,
                                           scene=cmd.scene, size=tuple(cmd.size), ray_model=cmd.target_ray_model,
                                           center_lps=center)
    else:
        target_renderer = DRRRenderer(volume, RenderSettings(scene=cmd.scene, size=tuple(cmd.size),
                                                             ray_model=cmd.target_ray_model), center_lps=center)
    moving = None if cmd.physics == "line" else PhysicsSettings(
        level=cmd.physics, noise=False, scatter_photons=REGISTER_SCATTER_PHOTONS)
    methods = {name: METHODS[name](volume, center, tuple(cmd.size), model=cmd.model, physics=moving)
               for name in cmd.method}
    physics_record = {"target_physics": cmd.target_physics if cmd.target_physics == "line" else asdict(physics),
                      "moving_physics": "line" if moving is None else asdict(moving)}
    result = evaluate(volume, methods, settings, Path(cmd.out), center_lps=center,
                      geometry=target_renderer.geometry, target_renderer=target_renderer, record=physics_record)
    print(result["table"])
    return [Path(cmd.out) / name for name in ("cases.csv", "summary.json", "table.md", "violins.png")]


@dataclass(frozen=True)
class RegisterCommand:
    """Defaults of ``ctxreg register``."""

    ct: str = field(metadata=opt(CT_HELP, group="input", metavar="PATH|phantom"))
    xray: str = field(metadata=opt(
        "X-ray: DICOM (geometry from its tags when present) or PNG/TIFF/JPEG", group="input", metavar="IMAGE"))
    label_map: str | None = field(default=None, metadata=opt(
        "label map on the CT's grid: its centroid is the anatomy centre", group="input", metavar="PATH"))
    center: tuple[float, float, float] | None = field(default=None, metadata=opt(
        "anatomy centre c in LPS", group="input", unit="mm", nargs=3, metavar=("X", "Y", "Z")))
    init: tuple[str, ...] = field(default=("ap",), metadata=opt(
        "start pose: 'ap' or six numbers PHI THETA PSI TX TY TZ", group="pose", nargs="+",
        unit="deg deg deg mm mm mm", metavar="ap|P"))
    method: str = field(default="cmaes", metadata=opt(
        "registration method", group="pose", choices=("cmaes", "contextual", "contextual+cmaes")))
    model: str | None = field(default=None, metadata=opt(
        "trained network checkpoint (ctxreg train) for the contextual methods", group="pose", metavar="CKPT"))
    restarts: int = field(default=REGISTER_RESTARTS, metadata=opt(
        "CMA-ES restarts (new seed, twice the population) while the final gradient NCC is below "
        f"{CMAESSettings.restart_below}: a search lost far from the start tries again", group="pose", metavar="N"))
    scene: str = field(default="cios_fusion", metadata=opt(
        "C-arm scene: the geometry where the image does not give it", group="geometry"))
    sdd: float | None = field(default=None, metadata=opt(
        "source-to-detector distance (overrides DICOM and scene)", group="geometry", unit="mm"))
    sod: float | None = field(default=None, metadata=opt(
        "source-to-isocentre distance (overrides DICOM and scene)", group="geometry", unit="mm"))
    pixel_spacing: float | None = field(default=None, metadata=opt(
        "detector pixel spacing (overrides DICOM and scene)", group="geometry", unit="mm"))
    size: int = field(default=128, metadata=opt(
        "longer side of the image the optimiser works on", group="geometry", unit="pixels"))
    physics: str = level_field(help=(
        "physics of the moving images: line (line-integral DRRs), poly (noise-free -log(I/I0) with "
        "the tube spectrum, 7 materials, CsI detector: beam hardening like the X-ray's) or full "
        "(poly + Monte Carlo scatter, same seed at every pose)"))
    kvp: float = physics_option("kvp")
    filter: tuple[str, ...] = physics_option("filter")
    anode_angle: float = physics_option("anode_angle")
    bins: int = physics_option("bins")
    detector_mm: float = physics_option("detector_mm")
    detector_mode: str = physics_option("detector_mode")
    scatter_photons: int = physics_option("scatter_photons", default=REGISTER_SCATTER_PHOTONS)
    scatter_voxel: float = physics_option("scatter_voxel")
    grid_ratio: float = physics_option("grid_ratio")
    label_material: tuple[str, ...] = physics_option("label_material")
    preprocess: tuple[str, ...] = field(default=("field", "median", "intensity", "normalize", "crop"), metadata=opt(
        "preprocessing steps in order: field (collimated field, text and saturation -> valid-pixel mask), "
        "median, intensity (decides raw / log / display and bone bright / dark, then log and/or invert), "
        "log, invert, normalize (over the mask), crop (to the mask)", group="image", nargs="*"))
    intensity: str = field(default="auto", metadata=opt(
        "what the pixel values are: linear (raw detector intensity: takes the log), log, display "
        "(a vendor's LUT); auto decides from the DICOM tags, then the image", group="image",
        choices=("auto", "linear", "log", "display")))
    polarity: str = field(default="auto", metadata=opt(
        "bone in the image as displayed: bone-bright (radiograph) or bone-dark (fluoroscopy, raw); auto "
        "decides from the DICOM tags, the image's noise, DRRs of the CT around the start and the file's "
        "modality, then checks by a coarse registration of the image and its inverse", group="image",
        choices=("auto", "bone-bright", "bone-dark")))
    out: str = field(default="out/register", metadata=opt(
        "folder for result.json, overlay.png (DRR edges and the field outline over the X-ray at its full "
        "resolution), checkerboard.png, convergence.png (and trajectory.npz, trajectory.png for the "
        "contextual methods)", group="output", metavar="DIR"))


def _parse_init(values: tuple[str, ...]) -> np.ndarray:
    from register.cmaes import RegistrationError

    if len(values) == 1 and values[0] == "ap":
        return np.zeros(6)
    try:
        x = np.array([float(v) for v in values])
    except ValueError:
        x = np.zeros(0)
    if x.shape != (6,) or not np.all(np.isfinite(x)):
        raise RegistrationError(f"--init {' '.join(values)}: give 'ap' or six finite numbers")
    return x


def run_register(cmd: RegisterCommand) -> list[Path]:
    import sys
    from dataclasses import asdict

    from register.cmaes import CMAESRegistration, CMAESSettings, RegistrationError
    from register.plots import checkerboard_png, convergence_plot, overlay_png
    from register.prepare import confirm_polarity, prepare_xray
    from register.xray_io import load_xray
    from sim.anatomy import anatomy_center
    from sim.atomic import write_json
    from sim.ct_io import load_ct_spec
    from sim.physics.options import check_level_options, label_materials, physics_settings
    from sim.render import DRRRenderer, RenderSettings

    init = _parse_init(cmd.init)
    check_level_options(cmd)
    physics = physics_settings(cmd, noise=False)
    materials = label_materials(cmd)
    steps = [str(n).strip().lower() for n in cmd.preprocess]
    if cmd.method != "cmaes" and cmd.model is None:
        raise RegistrationError(f"--method {cmd.method} needs a trained model: --model CHECKPOINT")
    volume = load_ct_spec(cmd.ct, label_map=cmd.label_map)
    center = np.asarray(cmd.center, float) if cmd.center is not None else anatomy_center(volume)
    xray = load_xray(cmd.xray)
    if not xray.attenuation_bright and not {"intensity", "log", "invert"} & set(steps):
        raise RegistrationError(f"{xray.source}: raw detector data (bone dark): add 'intensity' or 'log' to --preprocess")
    prepared = prepare_xray(xray, volume=volume, center_lps=center, init_params=init, scene=cmd.scene, steps=steps,
                            scale=cmd.intensity, polarity=cmd.polarity, size=cmd.size, sdd_mm=cmd.sdd,
                            sod_mm=cmd.sod, pixel_spacing_mm=cmd.pixel_spacing)
    prepared = confirm_polarity(prepared, volume, center, init, physics=physics, label_materials=materials)
    print(prepared.sources.line())
    for line in _input_lines(prepared):
        print(line)
    image, mask, geometry = prepared.image, prepared.mask, prepared.geometry
    size = (geometry.height, geometry.width)
    if cmd.method == "cmaes":
        engine = CMAESRegistration(volume, CMAESSettings(size=size, restarts=cmd.restarts), scene=cmd.scene,
                                   geometry=geometry, center_lps=center, physics=physics, label_materials=materials)
        result = engine.register(image, init, mask=mask)
    else:
        from dataclasses import replace

        from register.contextual import REFINE_SETTINGS, ContextualRegistration, ContextualSettings, NetworkPredictor

        refine = replace(REFINE_SETTINGS, size=size) if cmd.method == "contextual+cmaes" else None
        predictor = NetworkPredictor(cmd.model)
        mismatch = predictor.physics_mismatch(physics)
        if mismatch:
            print(f"ctxreg register: note: {mismatch}", file=sys.stderr)
        engine = ContextualRegistration(volume, predictor, ContextualSettings(keep_drrs=True),
                                        size=size, scene=cmd.scene, geometry=geometry, center_lps=center,
                                        refine=refine, physics=physics, label_materials=materials)
        result = engine.register(image, init, mask=mask)
    out = Path(cmd.out)
    written = []
    if result.trajectory is not None:
        from register.plots import trajectory_figure
        from sim.atomic import atomic_path

        with atomic_path(out / "trajectory.npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, params_deg_mm=result.trajectory["params"], g_rad_mm=result.trajectory["g"],
                                    drrs=result.trajectory["drrs"].astype(np.float32), xray=image.astype(np.float32))
        trajectory_figure(image, result.trajectory["drrs"], result.trajectory["params"], out / "trajectory.png")
        written = [out / "trajectory.npz", out / "trajectory.png"]
    # figures at the X-ray's own resolution: a line DRR with the X-ray's full geometry (its edges
    # are those of any physics level)
    full = prepared.full_geometry
    full_drr = DRRRenderer(volume, RenderSettings(size=(full.height, full.width)), center_lps=center,
                           geometry=full).render(result.pose)[0]
    overlay_png(xray.pixels, full_drr, out / "overlay.png", mask=prepared.full_mask)
    checkerboard_png(prepared.full_image, full_drr, out / "checkerboard.png", mask=prepared.full_mask)
    convergence_plot(result.history, out / "convergence.png")
    write_json(out / "result.json", {
        **result.to_dict(), "method": cmd.method, "ct": volume.source, "xray": xray.source, "init_params": init.tolist(),
        "anatomy_center_lps_mm": center.tolist(), "xray_input": prepared.summary(), "preprocessing": prepared.record,
        "moving_physics": {**asdict(physics), "label_materials": {str(k): v for k, v in (materials or {}).items()}},
        "geometry": {"sdd_mm": geometry.sdd_mm, "sod_mm": geometry.sod_mm, "height": geometry.height,
                     "width": geometry.width, "pixel_spacing_mm": geometry.pixel_spacing_mm,
                     "principal_point_uv": list(geometry.principal_point), "K": geometry.intrinsics().tolist()},
    })
    print(f"similarity {result.similarity:.4f} after {result.renders} renders; pose: "
          + " ".join(f"{v:.2f}" for v in result.params))
    return [out / "result.json", out / "overlay.png", out / "checkerboard.png", out / "convergence.png", *written]


def _input_lines(prepared) -> list[str]:
    """One line each for the field and the intensity decision (what a user should check first)."""
    lines = []
    fld = prepared.step("field")
    if fld is not None:
        kind = fld.get("kind")
        outside = f", {fld.get('outside')} outside" if fld.get("outside") else ""
        lines.append(f"field: {kind}{outside}; {100 * fld.get('valid_fraction', 0):.0f} % of the pixels valid")
    dec = prepared.step("intensity")
    if dec is not None:
        steps = " + ".join(dec["steps"]) or "nothing"
        lines.append(f"intensity: {dec['scale']} ({dec['scale_source']}), {dec['polarity']} "
                     f"({dec['polarity_source']}): {steps}")
    check = prepared.step("polarity_check")
    if check is not None:
        verdict = {"inverted": "inverted the image", "confirmed": "confirmed",
                   "inconclusive": "inconclusive, the decision stands"}[check["verdict"]]
        lines.append(f"polarity check by registration: {verdict} (similarity {check['similarity_as_decided']:.3f} "
                     f"as decided, {check['similarity_inverted']:.3f} inverted): {check['polarity']}")
    return lines
