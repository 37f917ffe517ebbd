"""The packages depend one way, sim -> learn -> register: no module imports upward (an AST scan
of every import statement, including imports inside functions)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: package -> the packages it must never import
FORBIDDEN = {"sim": ("learn", "register"), "learn": ("register",)}


def _imports(path: Path) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module":
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                found.append((node.lineno, node.args[0].value))
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_package_imports_upward(package):
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no modules found under {package}/"
    bad = [f"{p.relative_to(ROOT)}:{line} imports {name}"
           for p in files for line, name in _imports(p)
           if name.split(".")[0] in FORBIDDEN[package]]
    assert not bad, "imports against sim -> learn -> register:\n" + "\n".join(bad)


def test_the_scan_sees_imports_inside_functions(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def f():\n    from register.cli import main\n    import learn.model\n")
    assert [n for _, n in _imports(f)] == ["register.cli", "learn.model"]


# --------------------------------------------------------------------------------------------
# No import cycle: the module graph of each package, imports inside functions included
# --------------------------------------------------------------------------------------------

PACKAGES = ("sim", "learn", "register")


def _module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path, packages=PACKAGES) -> dict[str, set[str]]:
    """``module -> the modules it imports`` over every ``.py`` file of ``packages`` under ``root``.

    Every import statement counts, at module level or inside a function: ``import a.b.c`` names
    the longest of ``a.b.c``, ``a.b``, ``a`` that is a module of the packages; ``from a.b import
    c`` names ``a.b.c`` when that is a module (a submodule imported by name), else ``a.b``;
    relative imports are resolved. Imports of other packages and of a module itself are left out.
    """
    paths = {_module_name(root, p): p for pkg in packages for p in sorted((root / pkg).rglob("*.py"))}

    def known(name: str) -> str | None:
        while name and name not in paths:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for mod, path in paths.items():
        package = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
        out = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                out.update(known(a.name) for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
                out.update(f"{base}.{a.name}" if f"{base}.{a.name}" in paths else known(base) for a in node.names)
        graph[mod] = out - {None, mod}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One shortest cycle through each module that lies on a cycle, as ``[m, ..., m]``, deduplicated
    (the strongly connected components' members, each with a path back to itself)."""
    found, seen = [], set()
    for start in sorted(graph):
        parent, frontier = {start: None}, [start]
        path = None
        while frontier and path is None:  # breadth first: the shortest way back to start
            nxt = []
            for v in frontier:
                for w in sorted(graph.get(v, ())):
                    if w == start:
                        chain = []
                        while v is not None:
                            chain.append(v)
                            v = parent[v]
                        path = [*reversed(chain), start]
                        break
                    if w not in parent:
                        parent[w] = v
                        nxt.append(w)
                if path is not None:
                    break
            frontier = nxt
        if path is not None:
            i = path.index(min(path[:-1]))  # one spelling per cycle: start at its smallest module
            key = tuple(path[i:-1] + path[:i])
            if key not in seen:
                seen.add(key)
                found.append([*key, key[0]])
    return found


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycle(package):
    graph = import_graph(ROOT)
    assert any(m.startswith(package + ".") for m in graph), f"no modules found under {package}/"
    mine = [c for c in cycles(graph) if c[0].split(".")[0] == package]
    assert not mine, (f"import cycles in {package} (imports inside functions count: move the shared concept "
                      f"down into a module both import):\n" + "\n".join(" -> ".join(c) for c in mine))


def test_the_graph_sees_every_kind_of_import_and_names_each_cycle(tmp_path):
    pkg = tmp_path / "sim"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("import sim.b\n")
    (pkg / "b.py").write_text("def f():\n    from sim.sub import c\n")  # inside a function; a submodule
    (pkg / "sub" / "c.py").write_text("from .. import a\nfrom sim.sub.d import X\n")  # relative
    (pkg / "sub" / "d.py").write_text("import os\nX = 1\n")
    (pkg / "e.py").write_text("import sim.f\n")
    (pkg / "f.py").write_text("from sim import e\n")
    graph = import_graph(tmp_path, ("sim",))
    assert graph["sim.b"] == {"sim.sub.c"} and graph["sim.sub.c"] == {"sim.a", "sim.sub.d"}
    assert graph["sim.sub.d"] == set()
    assert cycles(graph) == [["sim.a", "sim.b", "sim.sub.c", "sim.a"], ["sim.e", "sim.f", "sim.e"]]


# --------------------------------------------------------------------------------------------
# sim/ by stage: its infrastructure the lowest layer, few flat modules
# --------------------------------------------------------------------------------------------


def test_sim_core_imports_nothing_of_the_project_but_itself():
    """sim.core (errors, atomic writes, options, outputs, progress, seeds, Dask) is what every package
    may import: it must not import them back."""
    graph = import_graph(ROOT)
    bad = {m: sorted(n for n in deps if not n.startswith("sim.core")) for m, deps in graph.items()
           if m.startswith("sim.core")}
    assert not any(bad.values()), bad


def test_sim_keeps_its_stages_in_folders_and_few_flat_modules():
    flat = sorted(p.name for p in (ROOT / "sim").glob("*.py"))
    assert len(flat) <= 10, flat
    assert {"core", "ct", "projection", "physics", "campaign"} <= {p.name for p in (ROOT / "sim").iterdir()
                                                                  if (p / "__init__.py").is_file()}


# --------------------------------------------------------------------------------------------
# Imports at the top: a project module imported inside a function says why on its line
# --------------------------------------------------------------------------------------------


def _late_project_imports(path: Path) -> list[tuple[int, str, bool]]:
    """``(line, module, says why)`` of every import of a project module inside a function of
    ``path``: it says why where a ``#`` comment stands on the statement's first or last line."""
    text = path.read_text()
    lines = text.splitlines()
    found = []
    for fn in ast.walk(ast.parse(text, filename=str(path))):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                if name.split(".")[0] in PACKAGES:
                    why = "#" in lines[node.lineno - 1] or "#" in lines[node.end_lineno - 1]
                    found.append((node.lineno, name, why))
    return sorted(set(found))


def test_every_late_import_of_a_project_module_says_why():
    files = [p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))]
    bad = [f"{p.relative_to(ROOT)}:{line} imports {name} inside a function without a comment saying why"
           for p in files for line, name, why in _late_project_imports(p) if not why]
    assert not bad, "\n".join(bad)


def test_the_late_import_scan_sees_a_silent_one_and_a_commented_one(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import sim.core\n\n\ndef f():\n    import numpy\n    from learn.model import x\n"
                 "    from register.cli import (main,  # loads torch\n                              run)\n")
    assert _late_project_imports(f) == [(6, "learn.model", False), (7, "register.cli", True)]
