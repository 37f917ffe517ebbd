"""Do two checkouts make the same outputs? A refactoring's check (issue 30: bit-identical images,
registrations and trainings).

    .venv/bin/python scripts/same_outputs.py make OUT        # in a checkout: its outputs into OUT
    .venv/bin/python scripts/same_outputs.py compare A B     # every output of A against B's
    .venv/bin/python scripts/same_outputs.py small --write   # the CI-sized set, tests/data/same_outputs_small.npz

``make`` runs, in the checkout the script lies in (its code first on ``PYTHONPATH``, ``register.cli:main``): the demo (a realistic
DICOM frame registered from AP), a 10-case ``ctxreg evaluate`` (contextual+cmaes on line DRRs of the
pelvis CT), a line, a poly and a full-physics ``ctxreg render``, the smoke campaign's shards (``ctxreg
simulate``), the smoke study's rows (``ctxreg study studies/smoke.toml``: two variants trained 2 steps,
evaluated on line DRRs and realistic frames), and two short trainings (3 steps of 4 pairs,
batched and per-pair realistic pairs, from ``configs/train_batched_gpu.toml``). Without
``../shared/data`` the built-in phantom stands in for the CT.

``compare`` checks every file of A against B: images and arrays byte for byte (NumPy archives
array by array), DICOM pixel for pixel and tag for tag (not the fresh UIDs, dates, times); checkpoints
tensor by tensor (``torch.load(weights_only=True)``); JSON, TOML and CSV value by value, leaving out
what a run measures of itself (keys naming seconds, times, dates; absolute paths to a file of the
same name); logs and Markdown tables (timings) are not compared. The tool bank that batched pairs
trace with Mitsuba differs from one process to the next in a few values (about 1e-4 mm, also
before any refactoring); ``make --tables DIR`` reuses a folder of cached tables so that the
batched training can be compared bit for bit. It prints one line per
file and exits 1 when anything differs or is missing.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CT = ROOT.parent / "shared" / "data" / "ct" / "pelvis_abdomen_3mm.nii.gz"
# keys a run records of itself, not of its result
VOLATILE = ("time", "seconds", "_s", "date", "path", "elapsed", "duration", "rate", "eta", "out", "command",
            "host", "machine", "version", "created", "config", "wall")


def _run(args: list[str], log) -> None:
    print("$", " ".join(args), flush=True)
    # this checkout's code, also where the virtual environment's editable install points elsewhere
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run(args, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=env)
    if r.returncode != 0:
        sys.exit(f"same_outputs: {' '.join(args)} failed (exit {r.returncode}); see the log")


def make(out: Path, tables: Path | None = None) -> None:
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    ctxreg = [sys.executable, "-c", "import sys; from register.cli import main; sys.exit(main())"]
    ct = str(CT) if CT.is_file() else "phantom"
    with open(out / "make.log", "w") as log:
        _run([*ctxreg, "demo", "--out", str(out / "demo"), "--ct", ct], log)
        _run([*ctxreg, "evaluate", "--ct", ct, "--cases", "10", "--method", "contextual+cmaes", "--out",
              str(out / "evaluate")], log)
        pose = ["-10", "5", "3", "4", "-6", "8"]
        _run([*ctxreg, "render", "--ct", ct, "--size", "96", "96", "--pose", *pose, "--out",
              str(out / "render" / "line.npy")], log)
        _run([*ctxreg, "render", "--ct", ct, "--size", "64", "64", "--pose", *pose, "--physics", "full",
              "--scatter-photons", "20000", "--seed", "3", "--out", str(out / "render" / "full.npy")], log)
        _run([*ctxreg, "render", "--ct", ct, "--size", "48", "48", "--pose", *pose, "--physics", "poly", "--seed",
              "5", "--out", str(out / "render" / "poly.npy")], log)
        _run([*ctxreg, "simulate", str(ROOT / "campaigns" / "smoke.toml"), "--out", str(out / "campaign")], log)
        _run([*ctxreg, "study", str(ROOT / "studies" / "smoke.toml"), "--out", str(out / "study")], log)
        base = tomllib.loads((ROOT / "configs" / "train_batched_gpu.toml").read_text())
        for pairs in ("batched", "per-pair"):
            folder = out / f"train_{pairs}"
            folder.mkdir(exist_ok=True)
            if tables is not None and pairs == "batched":  # the cached spectral table and tool banks
                import shutil

                shutil.copytree(tables, folder / "run" / "tables", dirs_exist_ok=True)
            cfg = dict(base["train"])
            cfg.update(dataset=str(ROOT / "campaigns" / "pelvis_vp.toml"), out=str(folder / "run"),
                       init_from=str(ROOT / "models" / "pelvis_line" / "model.pt"), pairs=pairs, batch_size=4,
                       iterations=3, val_pairs=4, val_every=3, checkpoint_every=3, subjects_per_batch=2)
            from sim.core.atomic import toml_value

            lines = ["[train]"] + [f"{k} = {toml_value(v)}" for k, v in cfg.items() if not isinstance(v, dict)]
            lines += ["[train.randomize]"] + [f"{k} = {toml_value(v)}" for k, v in cfg["randomize"].items()]
            (folder / "config.toml").write_text("\n".join(lines) + "\n")
            _run([*ctxreg, "train", str(folder / "config.toml"), "--device", "cpu"], log)
    print(f"outputs in {out}")


#: The CI-sized fixed set's arrays (``small``), checked bit for bit by ``tests/test_same_outputs.py``.
SMALL = ROOT / "tests" / "data" / "same_outputs_small.npz"


def small_outputs() -> dict[str, "np.ndarray"]:
    """The CI-sized fixed set, in this process, in seconds: renders of the built-in phantom (line and
    poly), the imaging chain on them (per-pair draws of each scatter kind, a fixed display chain),
    the preparation of the targets (one NumPy pair and the batch), a CMA-ES registration of the line
    frame, and a training step of the tiny network (one torch thread). Nothing here traces the tool
    bank with Mitsuba, whose chords differ from one process to the next in their last bits."""
    import numpy as np
    import torch

    from learn.model import pose_update_net
    from learn.online import prepare_like_registration
    from register.api import register_xray
    from register.xray.io import XRayImage
    from sim import load_ct, render
    from sim.physics.display import Collimator, DisplayChain
    from sim.projection.geometry import CArmGeometry
    from sim.randomize import DomainRandomization, apply_image, draw_tensors, image_rng

    torch.set_num_threads(1)
    out: dict[str, np.ndarray] = {}
    ct = load_ct("phantom")
    pose = [-10.0, 5.0, 3.0, 4.0, -6.0, 8.0]
    out["render_line"] = render(ct, pose, size=(48, 48))
    out["render_poly"] = render(ct, pose, size=(32, 32), physics="poly")
    raw = 2000.0 * np.exp(-out["render_line"].astype(np.float64))
    g = CArmGeometry(sdd_mm=1020.0, sod_mm=620.0, height=48, width=48, pixel_spacing_mm=8.0)
    dr = DomainRandomization.from_table({"scatter": {"none": 0.25, "kernel": 0.25, "sks": 0.25, "monte-carlo": 0.25},
                                         "unsharp": 0.5, "tools": 0.0})
    images, fields = [], []
    for i in range(8):
        d = dr.draw(3, i)
        sc = 60.0 + 0.05 * raw if d["scatter"] == "monte-carlo" else None
        image, field = apply_image(raw, 2000.0, d, image_rng(3, i), scatter=sc, geometry=g, gap_mm=300.0)
        images.append(image)
        fields.append(field)
    out["chain_per_pair"], out["chain_fields"] = np.stack(images), np.stack(fields)
    chain = DisplayChain(gamma=0.8, unsharp_sigma_px=2.0, unsharp_amount=0.6, shutter="white")
    out["chain_fixed"] = chain.apply(raw, 2000.0, Collimator(shape="circle", radius=0.4).mask(48, 48))
    current = out["render_line"].astype(np.float64)
    t, c = prepare_like_registration(images[0], fields[0], current, log_display=True, bone_dark=True)
    out["prepared_pair"] = np.stack([t, c])
    draws = [dr.draw(3, i) for i in range(8)]
    logs = draw_tensors(draws)["log"]
    bt, bc = prepare_like_registration(torch.from_numpy(np.stack(images).astype(np.float32)),
                                       torch.from_numpy(np.stack(fields)),
                                       torch.from_numpy(np.repeat(current[None], 8, 0).astype(np.float32)),
                                       log_display=logs, bone_dark=draw_tensors(draws)["polarity"] == 0)
    out["prepared_batch"] = torch.stack([bt, bc]).numpy()
    # tools off: the set pins the registration's arithmetic, not a default (the segmenter would see
    # this 48 px DRR enlarged to 256 px and take pieces of it)
    reg = register_xray(ct, XRayImage(pixels=out["render_line"], attenuation_bright=True), method="cmaes",
                        size=(32, 32), restarts=0, init=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0], tools="off")
    out["registration_pose"] = np.asarray(reg.result.pose, np.float64)
    torch.manual_seed(0)
    net = pose_update_net(backbone="tiny")
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    x = torch.from_numpy(out["prepared_batch"])[:, :4, None].float()
    loss = net(x[0], x[1]).g.square().mean()
    loss.backward()
    opt.step()
    weights = torch.cat([q.detach().flatten() for q in net.parameters()]).numpy()
    # the stepped weights by their SHA-256 (2 MB of random weights do not compress), and their first values
    out["train_step_sha256"] = np.frombuffer(hashlib.sha256(weights.tobytes()).digest(), np.uint8)
    out["train_step_loss"], out["train_step_head"] = np.float32(loss.item()), weights[:256]
    return out


def machine() -> str:
    """What decides the last bits of the set's floating-point values: the CPU (Dr.Jit's LLVM backend
    compiles the renders for the host's vector instructions, whose rounding of a few values differs
    from one instruction set to another), Dr.Jit's and NumPy's versions."""
    import platform

    import drjit
    import numpy as np

    model, flags = platform.processor() or "", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and not model:
                model = value.strip()
            elif key.strip() in ("flags", "Features"):
                flags.update(value.split())
    except OSError:
        pass
    isa = ",".join(f for f in ("avx512f", "avx2", "fma", "asimd") if f in flags)
    return f"{platform.machine()} {model} [{isa}] drjit {drjit.__version__} numpy {np.__version__}"


#: Keys of the committed set that are not outputs: where it was made (:func:`machine`).
SMALL_META = ("machine",)


def _within_last_bits(a, b) -> bool:
    """Whether ``a`` is ``b`` up to what another CPU's rounding makes of it (:func:`small_differences`)."""
    import numpy as np

    if a.dtype.kind in "iub":  # counts and masks: a render's last bit can move a rounding by one count
        d = np.abs(a.astype(np.int64) - b.astype(np.int64))
        return int(d.max(initial=0)) <= 1 and float((d > 0).mean()) <= 0.01
    scale = max(float(np.nanmax(np.abs(b))), 1e-30) if b.size else 1.0
    d = np.abs(a.astype(np.float64) - b.astype(np.float64))
    return float(np.nanmax(d, initial=0.0)) <= 1e-3 * scale and float((d > 1e-5 * scale).mean()) <= 0.01


def _same_pose(a, b) -> bool:
    """Whether two ``(4, 4)`` poses agree within 1 deg and 3 mm: a CMA-ES registration follows
    another path where a render's last bits differ, and ends within its precision (32 px, 4 mm
    voxels, each end about 1 deg and 5 mm from the truth): 0.1 deg and 1.2 mm apart between two
    CPUs, 0.57 deg and 0.8 mm between the AMD EPYC the set was made on and an Intel Xeon
    (2026-11-30, the same at 9d8cff9, before that day's changes)."""
    import numpy as np

    from sim.projection.se3 import rotation_error_deg

    return float(rotation_error_deg(a, b)) <= 1.0 and float(np.linalg.norm(a[:3, 3] - b[:3, 3])) <= 3.0


def small_differences(outputs: dict, reference: Path = SMALL, *, exact: bool | None = None) -> list[str]:
    """What of ``outputs`` (:func:`small_outputs`) is not the committed set's (one line each): bit for
    bit where the set was made on this machine (:func:`machine`, recorded in it; ``exact``
    overrides), else within the last bits (:func:`_within_last_bits`: floating-point arrays within
    0.1 % of their largest value, at most 1 % of their values beyond 1e-5 of it; counts and masks
    within one count on at most 1 % of their values; the registration's pose within 1 deg and 3
    mm, :func:`_same_pose`; the training step's hash not compared, its first values are). Another
    CPU rounds a few render values differently (seen: 2 of 2304, 4.8e-7, about 2 float32 ulps),
    which moves a display value by one count here and there downstream."""
    import numpy as np

    with np.load(reference) as ref:
        want = {k: ref[k] for k in ref.files}
    made_on = str(want["machine"]) if "machine" in want else None
    if exact is None:
        exact = made_on == machine()
    want = {k: v for k, v in want.items() if k not in SMALL_META}
    outputs = {k: v for k, v in outputs.items() if k not in SMALL_META}
    lines = [f"{k}: only in {'the committed set' if k in want else 'this run'}" for k in sorted(set(want) ^ set(outputs))]
    for k in sorted(set(want) & set(outputs)):
        a, b = np.asarray(outputs[k]), want[k]
        if a.shape != b.shape or a.dtype != b.dtype:
            lines.append(f"{k}: {a.dtype} {a.shape} against {b.dtype} {b.shape}")
        elif not np.array_equal(a, b, equal_nan=True):
            if not exact and (k == "train_step_sha256" or (_same_pose(a, b) if k == "registration_pose"
                                                            else _within_last_bits(a, b))):
                continue
            d = np.abs(a.astype(np.float64) - b.astype(np.float64))
            lines.append(f"{k}: {int((a != b).sum())} of {a.size} values differ, at most {np.nanmax(d):.3g}")
    if not exact:
        print(f"same_outputs: the set was made on {made_on or 'another machine'}, this is {machine()}: compared "
              "within the last bits")
    for line in lines:
        print("DIFFERS", line)
    return lines


def _volatile(key: str) -> bool:
    k = key.lower()
    return any(v in k for v in VOLATILE)


def _same(a, b, where: str, diffs: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if _volatile(str(k)):
                continue
            if k == "sha256" and "settings" in a:  # a study variant's fingerprint of its settings, paths
                continue  # included: the settings themselves are compared
            if k not in a or k not in b:
                diffs.append(f"{where}.{k}: only in {'B' if k not in a else 'A'}")
            else:
                _same(a[k], b[k], f"{where}.{k}", diffs)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            diffs.append(f"{where}: {len(a)} against {len(b)} items")
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]", diffs)
    elif isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        pass
    elif isinstance(a, str) and isinstance(b, str) and a.startswith("/") and b.startswith("/") \
            and Path(a).name == Path(b).name:
        pass  # the same file in the other checkout or output folder
    elif a != b:
        diffs.append(f"{where}: {a!r} against {b!r}")


def _load(path: Path):
    if path.suffix == ".json":
        return json.loads(path.read_text())
    if path.suffix == ".toml":
        return tomllib.loads(path.read_text())
    if path.suffix == ".csv":
        with open(path) as f:
            return list(csv.DictReader(f))
    return None


def _compare_file(a: Path, b: Path) -> list[str]:
    if a.suffix == ".pt":
        import torch

        sa, sb = torch.load(a, weights_only=True, map_location="cpu"), torch.load(b, weights_only=True,
                                                                                map_location="cpu")
        diffs: list[str] = []

        def walk(x, y, where):
            if isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor):
                if x.shape != y.shape or not torch.equal(x, y):
                    diffs.append(f"{where}: tensors differ")
            elif isinstance(x, dict) and isinstance(y, dict):
                for k in sorted(set(x) | set(y), key=str):
                    if not _volatile(str(k)):
                        walk(x.get(k), y.get(k), f"{where}.{k}")
            elif isinstance(x, (list, tuple)) and isinstance(y, (list, tuple)) and len(x) == len(y):
                for i, (u, v) in enumerate(zip(x, y)):
                    walk(u, v, f"{where}[{i}]")
            elif x != y:
                diffs.append(f"{where}: {x!r} against {y!r}"[:300])

        walk(sa, sb, "")
        return diffs
    if a.suffix == ".npz":  # a zip: its members' timestamps differ; the arrays must not
        import numpy as np

        with np.load(a) as za, np.load(b) as zb:
            if sorted(za.files) != sorted(zb.files):
                return [f"arrays {sorted(za.files)} against {sorted(zb.files)}"]
            return [f"{k}: arrays differ" for k in za.files
                    if not np.array_equal(za[k], zb[k], equal_nan=za[k].dtype.kind in "fc")]
    if a.suffix in (".h5", ".hdf5"):  # a campaign shard: every dataset's values and every attribute (the
        # file's bytes carry HDF5's modification times)
        import h5py
        import numpy as np

        diffs: list[str] = []
        with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
            def visit(name, obj):
                other = fb.get(name)
                if other is None:
                    diffs.append(f"{name}: only in A")
                    return
                if isinstance(obj, h5py.Dataset) and not np.array_equal(obj[()], other[()]):
                    diffs.append(f"{name}: values differ")
                for k, v in obj.attrs.items():
                    if not _volatile(k) and not np.array_equal(np.asarray(v), np.asarray(other.attrs.get(k))):
                        diffs.append(f"{name}@{k}: differs")
            fa.visititems(visit)
            fb.visititems(lambda name, _: None if name in fa else diffs.append(f"{name}: only in B"))
        return diffs
    if a.suffix == ".dcm":  # every element but the fresh UIDs, dates and times; the pixels exactly
        import pydicom

        da, db = pydicom.dcmread(a), pydicom.dcmread(b)
        diffs = [] if (da.pixel_array == db.pixel_array).all() else ["pixels differ"]
        for elem in da.iterall():
            if elem.VR in ("UI", "DA", "TM", "DT") or elem.tag == (0x7FE0, 0x0010):
                continue
            other = db.get(elem.tag)
            if other is None or other.value != elem.value:
                diffs.append(f"{elem.keyword or elem.tag}: differs")
        return diffs
    data = _load(a)
    if data is not None:
        diffs = []
        _same(data, _load(b), "", diffs)
        return diffs
    if a.suffix in (".log", ".txt", ".gif", ".md", ".sh") or a.name == ".ctxreg.lock":  # logs and tables carry
        # rates and times (the numbers are in the JSON and CSV beside them); the GIF its frame times; a run's lock
        # file its process and host; a study's commands.sh the output folder's path
        return []
    return [] if a.read_bytes() == b.read_bytes() else ["bytes differ"]


def compare(a_dir: Path, b_dir: Path) -> int:
    for d in (a_dir, b_dir):
        if not d.is_dir():
            print(f"same_outputs: {d} is not a folder of outputs (make one with: make OUT)", file=sys.stderr)
            return 2
    files_a = {p.relative_to(a_dir) for p in a_dir.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b_dir) for p in b_dir.rglob("*") if p.is_file()}
    bad = 0
    for rel in sorted(files_a | files_b):
        if rel not in files_a or rel not in files_b:
            print(f"MISSING {rel}: only in {'A' if rel in files_a else 'B'}")
            bad += 1
            continue
        diffs = _compare_file(a_dir / rel, b_dir / rel)
        print(f"{'same   ' if not diffs else 'DIFFERS'} {rel}" + (f": {'; '.join(diffs[:5])}" if diffs else ""))
        bad += bool(diffs)
    print(f"{len(files_a | files_b) - bad} of {len(files_a | files_b)} files the same")
    return 1 if bad else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make", help="this checkout's outputs into OUT")
    m.add_argument("out", type=Path)
    m.add_argument("--tables", type=Path, help="a batched run's cached tables folder to reuse (another make's "
                                               "OUT/train_batched/run/tables)")
    sm = sub.add_parser("small", help="the CI-sized set (tests/test_same_outputs.py checks it bit for bit on the "
                                      "machine it was made on, within the last bits elsewhere)")
    sm.add_argument("--write", action="store_true", help=f"write it to {SMALL.relative_to(ROOT)} (after a change "
                                                          "that changes outputs on purpose; say why in the commit)")
    c = sub.add_parser("compare", help="the outputs of A against B's")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = p.parse_args()
    if args.cmd == "make":
        sys.path.insert(0, str(ROOT))
        make(args.out, args.tables)
        return 0
    if args.cmd == "small":
        # one thread everywhere, whatever the caller's environment: the renders' last bits follow the
        # thread count (OMP_NUM_THREADS=1 moved 3 of 2304 line-render values by 4.8e-7), and a test
        # session may have set it (learn.distributed.launch sets it for its ranks)
        os.environ["OMP_NUM_THREADS"] = "1"
        sys.path.insert(0, str(ROOT))
        outputs = small_outputs()
        if args.write:
            import numpy as np

            from sim.core.atomic import atomic_path

            SMALL.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(SMALL) as tmp:
                np.savez_compressed(tmp, **outputs, machine=np.array(machine()))
            print(f"wrote {SMALL.relative_to(ROOT)}: {', '.join(outputs)}")
            return 0
        return 0 if not small_differences(outputs) else 1
    return compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
