"""``ctxreg evaluate`` and ``ctxreg register``: defaults (one dataclass each) and their runs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.cli import CT_HELP
from sim.cliargs import opt


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
        "registration methods to compare", group="protocol", nargs="+", choices=("cmaes",)))
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
    out: str = field(default="out/evaluate", metadata=opt(
        "folder for cases.csv, summary.json, table.md, violins.png", group="output", metavar="DIR"))


def run_evaluate(cmd: EvaluateCommand) -> list[Path]:
    from register.evaluate import METHODS, EvaluationSettings, evaluate
    from sim.anatomy import anatomy_center
    from sim.ct_io import load_ct_spec
    from sim.render import DRRRenderer, RenderSettings

    settings = EvaluationSettings(cases=cmd.cases, seed=cmd.seed, size=tuple(cmd.size), start=cmd.start,
                                  local_rot_deg=cmd.local_rot, local_trans_mm=cmd.local_trans)
    volume = load_ct_spec(cmd.ct, label_map=cmd.label_map)
    center = np.asarray(cmd.center, float) if cmd.center is not None else anatomy_center(volume)
    target_renderer = DRRRenderer(volume, RenderSettings(scene=cmd.scene, size=tuple(cmd.size)), center_lps=center)
    methods = {name: METHODS[name](volume, center, tuple(cmd.size)) for name in cmd.method}
    result = evaluate(volume, methods, settings, Path(cmd.out), center_lps=center,
                      geometry=target_renderer.geometry, target_renderer=target_renderer)
    print(result["table"])
    return [Path(cmd.out) / name for name in ("cases.csv", "summary.json", "table.md", "violins.png")]
