"""The package's architecture, checked by tools rather than by review:

* no module takes a private name (``_name``) of another module of the project, by
  ``from module import _name`` or ``module._name`` (a name another module needs is public);
* the import layers and the pure-model rule of ``pyproject.toml`` ``[tool.importlinter]`` hold
  (``lint-imports``; ``make test`` runs it too).

Test modules are exempt from the first rule: a test may reach into what it tests.
"""

import ast
import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCANNED = ("jprt", "experiments")


def _sources() -> list[str]:
    paths = []
    for top in SCANNED:
        for folder, _, files in os.walk(os.path.join(ROOT, top)):
            paths += [os.path.join(folder, f) for f in sorted(files) if f.endswith(".py")]
    return paths


def _module_name(path: str) -> str:
    name = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
    return name[: -len(".__init__")] if name.endswith(".__init__") else name


def _project_modules() -> set[str]:
    """Every module of jprt/ by its dotted name, and every experiment module by the bare name its
    siblings import it under (experiments import each other as in ``python file.py``)."""
    names = set()
    for path in _sources():
        name = _module_name(path)
        names.add(name.split(".", 1)[1] if name.startswith("experiments.") else name)
    return names


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_uses(source: str, modules: set[str], filename: str = "<source>") -> list[tuple[int, str]]:
    """(line, what) of every private name of a project module used in ``source``: ``from m import
    _x`` and ``m._x`` where ``m`` is bound to a project module by an import (``import a.b as m``,
    ``from a import b``, ``import a.b`` then ``a.b._x``)."""
    tree = ast.parse(source, filename)
    uses, bound = [], {}

    def project(name: str) -> bool:
        return name in modules or name.split(".")[0] == "jprt"

    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and project(node.module):
            for alias in node.names:
                if _private(alias.name):
                    uses.append((node.lineno, f"from {node.module} import {alias.name}"))
                elif f"{node.module}.{alias.name}" in modules:
                    bound[alias.asname or alias.name] = f"{node.module}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if project(alias.name):
                    if alias.asname:
                        bound[alias.asname] = alias.name
                    else:
                        bound[alias.name.split(".")[0]] = alias.name.split(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            parts, value = [], node.value
            while isinstance(value, ast.Attribute):
                parts.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in bound:
                module = ".".join([bound[value.id], *reversed(parts)])
                if project(module):
                    uses.append((node.lineno, f"{module}.{node.attr}"))
    return sorted(uses)


def test_no_private_name_crosses_a_module():
    modules = _project_modules()
    found = []
    for path in _sources():
        with open(path) as f:
            source = f.read()
        found += [f"{os.path.relpath(path, ROOT)}:{line}: {what}" for line, what in private_uses(source, modules, path)]
    assert not found, "private names taken from another module (make them public or move them):\n" + "\n".join(found)


def test_the_scan_finds_each_form():
    modules = {"jprt.render.lightmap", "jprt.render", "rrf_common"}
    source = ("from jprt.render.lightmap import _eps, intersect\n"
              "from jprt.render import lightmap\n"
              "import jprt.render.lightmap as lm\n"
              "import jprt.render.lightmap\n"
              "import rrf_common\n"
              "lightmap._intersect\nlm._eps\njprt.render.lightmap._eps\nrrf_common._pairs\n"
              "lightmap.__doc__\nlightmap.intersect\nother._private\n")
    assert [what for _, what in private_uses(source, modules)] == [
        "from jprt.render.lightmap import _eps", "jprt.render.lightmap._intersect", "jprt.render.lightmap._eps",
        "jprt.render.lightmap._eps", "rrf_common._pairs"]


def test_every_module_has_a_layer():
    """Each top-level module and package of jprt is named in the layers contract, so none escapes
    the check by being left out."""
    import tomllib

    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        contracts = tomllib.load(f)["tool"]["importlinter"]["contracts"]
    layers = next(c for c in contracts if c["type"] == "layers")
    named = {m.strip().strip("()") for layer in layers["layers"] for m in layer.replace("|", ":").split(":")}
    package = os.path.join(ROOT, "jprt")
    modules = {os.path.splitext(n)[0] for n in os.listdir(package)
               if (n.endswith(".py") and n != "__init__.py") or os.path.isfile(os.path.join(package, n, "__init__.py"))}
    assert modules - named == set(), f"jprt modules without a layer in pyproject.toml: {sorted(modules - named)}"
    assert named - modules == set(), f"layers name modules jprt does not have: {sorted(named - modules)}"


def test_import_layers_hold():
    """``lint-imports`` keeps every contract of pyproject.toml (the layers, pure models)."""
    exe = shutil.which("lint-imports", path=os.path.dirname(sys.executable)) or shutil.which("lint-imports")
    if exe is None:
        pytest.skip("lint-imports is not installed (pip install import-linter, in the test extra)")
    done = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "0 broken" in done.stdout
