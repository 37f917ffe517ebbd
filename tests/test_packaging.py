"""An ordinary (non-editable) install: the wheel built from the working tree holds every package
and data file of the source tree, and ``ctxreg`` installed from it runs away from the repository.

The editable install of ``scripts/setup.sh`` maps the packages onto the source tree, so it cannot
show a package missing from ``pyproject.toml``; this test builds and installs a real wheel. It
downloads nothing: the build uses the setuptools of the running environment
(``--no-build-isolation``), and the fresh virtual environment sees the already installed
third-party packages through one path line in a ``.pth`` file (a path line does not process that
directory's own ``.pth`` files, so the editable finder of ctxreg there stays inactive; checked).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.conftest import REPO

# Top-level package directories that must not ship (mirrors pyproject's packages.find exclude).
NOT_SHIPPED = {"tests"}
# Never copied into the build tree: the VCS, environments, caches, outputs, data.
SKIP_ANYWHERE = {"__pycache__", ".pytest_cache"}
SKIP_AT_ROOT = {".git", ".venv", "runs", "build", "dist", "out", "shared"}


def _copy_source(dst: Path) -> Path:
    """The working tree without environments, caches and outputs: the build writes its build/ and
    egg-info there, not into the repository."""

    def ignore(folder: str, names: list[str]) -> set[str]:
        skip = {n for n in names if n in SKIP_ANYWHERE or n.endswith((".pyc", ".egg-info"))}
        if Path(folder).resolve() == REPO:
            skip |= SKIP_AT_ROOT & set(names)
        return skip

    shutil.copytree(REPO, dst, ignore=ignore, symlinks=True)
    return dst


def _source_packages(root: Path) -> dict[str, list[str]]:
    """Every importable package directory under ``root`` (an ``__init__.py`` in it and in each
    parent up to ``root``), except :data:`NOT_SHIPPED`: its relative path (``sim/physics``) ->
    the names of its files (Python and data)."""
    out: dict[str, list[str]] = {}

    def walk(d: Path, rel: str) -> None:
        out[rel] = sorted(p.name for p in d.iterdir() if p.is_file() and p.suffix != ".pyc")
        for sub in sorted(d.iterdir()):
            if sub.is_dir() and (sub / "__init__.py").is_file():
                walk(sub, f"{rel}/{sub.name}")

    for top in sorted(root.iterdir()):
        if top.is_dir() and top.name not in NOT_SHIPPED and (top / "__init__.py").is_file():
            walk(top, top.name)
    return out


def _run(cmd: list, cwd: Path, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))} -> {r.returncode}\n{r.stdout}\n{r.stderr}"
    return r


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """(wheel path, packages of the source tree it was built from)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = _copy_source(tmp / "src")
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
          "-q", "-w", tmp / "dist", src], cwd=tmp, timeout=300)
    wheels = list((tmp / "dist").glob("ctxreg-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0], _source_packages(src)


def test_the_wheel_holds_every_package_and_data_file_of_the_source_tree(built):
    wheel, packages = built
    assert {"sim", "sim/physics", "sim/campaign", "sim/projection/integrators", "learn", "register",
            "scenes"} <= set(packages)  # the derivation itself finds the known packages
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(f"{pkg}/{f}" for pkg, files in packages.items() for f in files
                     if f"{pkg}/{f}" not in names)
    assert not missing, f"not in the wheel (pyproject.toml [tool.setuptools.packages.find] / package-data): {missing}"
    assert "scenes/cios_fusion.xml" in names
    tops = {n.split("/")[0] for n in names}
    dist_info = {t for t in tops if t.endswith(".dist-info")}
    assert len(dist_info) == 1 and tops - dist_info == {p for p in packages if "/" not in p}, tops
    extra = sorted(n for n in names if not n.startswith(tuple(dist_info))
                   and n.rsplit("/", 1)[0] not in packages)
    assert not extra, f"files outside the source packages: {extra}"
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]


@pytest.fixture(scope="module")
def installed(built, tmp_path_factory):
    """A fresh virtual environment (the running interpreter's base Python) with the wheel
    installed and the running environment's third-party packages on its path: (venv, workdir)."""
    wheel, _ = built
    tmp = tmp_path_factory.mktemp("venv")
    venv = tmp / "venv"
    base = getattr(sys, "_base_executable", None) or sys.executable
    r = subprocess.run([base, "-m", "venv", "--without-pip", str(venv)], capture_output=True, text=True,
                       timeout=120)
    if r.returncode != 0:
        pytest.skip(f"cannot create a virtual environment with {base}: {r.stderr.strip()[-300:]}")
    py = venv / "bin" / "python"
    # pip of the running environment installs into the new one; nothing is downloaded
    _run([sys.executable, "-m", "pip", "--python", py, "install", "--no-deps", "--no-index", "-q", wheel],
         cwd=tmp)
    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=tmp).stdout.strip())
    deps = sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]})
    # after the install, so that pip never saw (or tried to replace) the ctxreg of the running env
    (site / "_ctxreg_test_deps.pth").write_text("".join(f"{d}\n" for d in deps))
    work = tmp / "work"
    work.mkdir()
    return venv, work


def _env() -> dict:
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}


def test_the_installed_packages_come_from_the_new_environment_not_the_source(built, installed):
    venv, work = installed
    _, packages = built
    mods = sorted(p.replace("/", ".") for p in packages)
    code = ("import importlib, json, sys; mods = %r\n"
            "files = {m: importlib.import_module(m).__file__ for m in mods}\n"
            "import scenes\n"
            "print(json.dumps({'files': files, 'scenes': scenes.available(),\n"
            "  'editable': [m for m in sys.modules if m.startswith('__editable__')]\n"
            "              + [type(f).__module__ for f in sys.meta_path if 'editable' in type(f).__module__]}))"
            % mods)
    info = json.loads(_run([venv / "bin" / "python", "-c", code], cwd=work, env=_env()).stdout)
    assert info["editable"] == [], "the editable finder of the development install is active"
    site = venv.resolve()
    for mod, file in info["files"].items():
        path = Path(file).resolve()
        assert path.is_relative_to(site) and not path.is_relative_to(REPO), (mod, file)
    assert info["scenes"] == sorted(p.stem for p in (REPO / "scenes").glob("*.xml"))


def test_the_installed_ctxreg_runs_and_renders_as_the_source_tree_does(installed, tmp_path):
    venv, work = installed
    ctxreg = venv / "bin" / "ctxreg"
    r = _run([ctxreg, "--help"], cwd=work, env=_env())
    for cmd in ("render", "simulate", "register", "evaluate", "train", "accuracy", "demo"):
        assert cmd in r.stdout, cmd
    out = tmp_path / "x.png"
    _run([ctxreg, "render", "--ct", "phantom", "--size", 32, 32, "--out", out], cwd=work, env=_env())
    assert out.is_file() and out.with_suffix(".json").is_file()
    # the same image and geometry as the source tree's ctxreg (the development install)
    ref = tmp_path / "ref.png"
    _run([sys.executable, "-m", "register.cli", "render", "--ct", "phantom", "--size", 32, 32, "--out", ref],
         cwd=REPO)
    img = np.asarray(Image.open(out))
    assert img.shape == (32, 32) and img.max() == 255
    np.testing.assert_array_equal(img, np.asarray(Image.open(ref)))
    assert json.loads(out.with_suffix(".json").read_text()) == json.loads(ref.with_suffix(".json").read_text())
