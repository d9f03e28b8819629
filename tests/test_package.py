"""The package as a whole (``ti_dk/__init__.py``): its rooms, their sizes, who imports whom, the
map of it in ``docs/where-things-are.md``, and what a wheel ships (the scene files)."""
import ast
import importlib
import importlib.util
import os
import re
import shutil
import subprocess
import sys

import ti_dk

from .helpers import ROOT

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

PACKAGE = ROOT / "ti_dk"
MODULES = sorted(PACKAGE.rglob("*.py"))
LIMITS = {"module": 500, "class": 250, "function": 60}  # lines, docstrings included


def _name(path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path) -> set[str]:
    """The ti_dk modules ``path`` imports at module level or inside functions (resolved)."""
    name, tree = _name(path), ast.parse(path.read_text())
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = pkg.split(".")
            if node.level:
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if not mod.startswith("ti_dk"):
                continue
            for a in node.names:
                sub = f"{mod}.{a.name}"
                found.add(sub if (ROOT / (sub.replace(".", "/") + ".py")).exists()
                          or (ROOT / sub.replace(".", "/")).is_dir() else mod)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("ti_dk"))
    return found - {name}


def test_no_room_too_big():
    too_big = []
    for path in MODULES:
        src = path.read_text()
        if len(src.splitlines()) > LIMITS["module"]:
            too_big.append(f"{path.name}: {len(src.splitlines())} lines")
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, (ast.ClassDef, ast.FunctionDef)):
                kind = "class" if isinstance(node, ast.ClassDef) else "function"
                n = node.end_lineno - node.lineno + 1
                if n > LIMITS[kind]:
                    too_big.append(f"{_name(path)}.{node.name}: {n} lines")
    assert not too_big


def test_subpackages_and_no_import_circles():
    packages = sorted(p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists())
    assert len(packages) >= 3, packages
    graph = {_name(p): _imports(p) for p in MODULES}
    graph = {k: {m for m in v if m in graph} for k, v in graph.items()}
    graph.pop("ti_dk")  # the top re-exports the public API; no module inside imports it
    done: set[str] = set()

    def visit(m, stack):
        for n in sorted(graph[m] - {"ti_dk"}):
            assert n not in stack, " -> ".join(stack + [n])
            if n not in done:
                visit(n, stack + [n])
        done.add(m)

    for m in graph:
        visit(m, [m])


LAYERS = ("core", "pools", "methods", "hybrid", "scene", "output", "control")  # each imports only its own and those before


def test_subpackages_import_only_their_own_layer_and_those_below():
    """Every ti_dk import of a module in subpackage X goes to X or a layer below it (none to the top,
    ``ti_dk/__init__.py`` and ``ti_dk/tradeoff.py``, which sit above every layer). The one exception: a
    ``__main__`` module is an entry point (``python -m ti_dk.scene`` runs ``ti_dk.control.cli``)."""
    packages = sorted(p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists())
    assert sorted(LAYERS) == packages
    up = []
    for path in MODULES:
        parts = _name(path).split(".")
        if len(parts) < 2 or path.name == "__main__.py" or parts[1] not in LAYERS:
            continue
        for m in sorted(_imports(path)):
            target = m.split(".")
            if len(target) < 2 or target[1] not in LAYERS or LAYERS.index(target[1]) > LAYERS.index(parts[1]):
                up.append(f"{_name(path)} ({parts[1]}) imports {m}")
    assert not up, "imports up the layers " + " < ".join(LAYERS) + ": " + "; ".join(up)


def test_every_import_of_ti_dk_names_a_module_that_exists():
    missing = [f"{_name(p)}: {m}" for p in MODULES for m in _imports(p)
               if not ((ROOT / (m.replace(".", "/") + ".py")).exists() or (ROOT / m.replace(".", "/") / "__init__.py").exists())]
    assert not missing


def test_no_module_reaches_into_another_modules_private_names():
    reaches = []
    for path in MODULES:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("ti_dk")):
                reaches += [f"{_name(path)}: {a.name}" for a in node.names if a.name.startswith("_")]
    assert not reaches


def _resolves(name: str) -> bool:
    """Whether dotted ``name`` is a module of ti_dk or an object in one, down to its last part: read
    as attributes from the package down, a module imported only where no attribute has the name (an
    import binds the module on its package: ``ti_dk.tradeoff`` must stay the function)."""
    obj = ti_dk
    for part in name.split(".")[1:]:
        if hasattr(obj, part):
            obj = getattr(obj, part)
        elif hasattr(obj, "__path__") and importlib.util.find_spec(f"{obj.__name__}.{part}") is not None:
            obj = importlib.import_module(f"{obj.__name__}.{part}")
        else:
            return False
    return True


def test_every_dotted_ti_dk_name_in_a_docstring_resolves():
    """Every ``ti_dk.…`` a docstring names (``:func:`ti_dk.control.options.check_options```, or in
    prose) is a module or an object that exists: no dead names after a move or a rename."""
    dead = []
    for path in MODULES + sorted((ROOT / "studies").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                for name in re.findall(r"\bti_dk(?:\.\w+)+", ast.get_docstring(node) or ""):
                    if "__main__" not in name and not _resolves(name):
                        dead.append(f"{path.relative_to(ROOT)}: {name}")
    assert not dead


def test_layout_names_every_module_once():
    page = (ROOT / "docs" / "where-things-are.md").read_text()
    layout = page[page.index("## Layout"):]
    listed = [line.split()[0] for line in layout.splitlines() if re.match(r"(ti_dk|studies)/\S+\.py", line)]
    tree = sorted(str(p.relative_to(ROOT)) for d in ("ti_dk", "studies") for p in (ROOT / d).rglob("*.py"))
    assert sorted(listed) == tree


def test_public_api_is_importable_from_the_top():
    for name in ("load_scene", "run", "tradeoff", "init", "Scene", "Result", "ConfigError", "OutputError",
                 "SimulationError", "available_scenes", "make_solver"):
        assert getattr(ti_dk, name) is not None
    # not shadowed by a subpackage or module of that name (ti_dk/tradeoff.py is the command line)
    assert callable(ti_dk.run) and callable(ti_dk.load_scene) and callable(ti_dk.tradeoff)


def test_pyproject_ships_every_subpackage_and_the_scene_files():
    """A wheel holds the subpackages pyproject.toml names: every one under ti_dk/, and the top-level
    scenes/ folder (its .toml files as package data) as ti_dk.scenes."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    subpackages = {_name(p) for p in PACKAGE.rglob("__init__.py")}
    assert set(tool["packages"]) == subpackages | {"ti_dk.scenes"}
    mapped = ROOT / tool["package-dir"]["ti_dk.scenes"]
    assert (mapped / "__init__.py").exists() and mapped == ROOT / "scenes"
    assert tool["package-data"]["ti_dk.scenes"] == ["*.toml"]


# how an installed ti_dk finds ti_dk.scenes: setuptools' editable finder maps it to the folder of
# package-dir; a wheel puts it in site-packages/ti_dk/scenes. Here it maps to a folder of our own.
_MAPPED_FINDER = """
import importlib.util, sys
class Mapped:
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name == "ti_dk.scenes":
            return importlib.util.spec_from_file_location(name, sys.argv[1] + "/__init__.py",
                                                          submodule_search_locations=[sys.argv[1]])
sys.meta_path.insert(0, Mapped)  # before an editable install's own finder
import ti_dk
from ti_dk.scene import schema
print(schema.SCENE_DIR, ti_dk.available_scenes(), ti_dk.load_scene("packaged1d").grid.cells)
"""


def test_scene_files_are_found_through_importlib_resources(tmp_path):
    """With ti_dk.scenes importable (any installed ti_dk), the scenes are that package's files, not
    the checkout's folder: a package holding one renamed scene lists exactly that one."""
    data = tmp_path / "scenes"
    data.mkdir()
    shutil.copy(ROOT / "scenes" / "__init__.py", data)
    (data / "packaged1d.toml").write_text((ROOT / "scenes" / "void1d.toml").read_text())
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", _MAPPED_FINDER, str(data)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == [str(data), "['packaged1d']", "(100,)"]


def test_docs_cite_nothing_a_stranger_cannot_see_and_write_one_time_unit():
    """No issue numbers or project-private paths in the documentation (benchmarks.md names the
    sections of benchmarks/RESULTS.md, which carry them), and the time unit written one way,
    L²/(2D), in the docs, the code and the frames."""
    private = re.compile(r"\b[Ii]ssues? \d+|\bshared/")
    cited = [f"{p.name}: {m.group()}" for p in (ROOT / "docs").rglob("*.md") if p.name != "benchmarks.md"
             for m in private.finditer(p.read_text())]
    assert not cited
    texts = [*(ROOT / "docs").rglob("*.md"), *MODULES, ROOT / "README.md"]
    assert not [p.name for p in texts if re.search(r"L(²|\^2)/2D", p.read_text())]
