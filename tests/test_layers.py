"""The package's one-way flow: a module imports only from its own subpackage or those below it."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import crchfl_sumo
from crchfl_sumo import LAYERS

PACKAGE = Path(crchfl_sumo.__file__).parent


def imported_modules(path: Path) -> set[str]:
    """Every crchfl_sumo module a file imports, at its top or inside a function."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
        elif isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"{path}: relative import; the package imports absolutely")
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return {n for n in names if n == "crchfl_sumo" or n.startswith("crchfl_sumo.")}


def layer_of(module: str) -> int:
    """Index of a dotted module's subpackage in LAYERS (crchfl_sumo itself: above them all)."""
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 else len(LAYERS)


def modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        out.append((".".join(p for p in rel.parts if p != "__init__"), path))
    return out


def test_every_subpackage_has_a_layer_and_every_layer_a_subpackage():
    subpackages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert subpackages == set(LAYERS)


def test_no_module_imports_from_a_subpackage_above_its_own():
    upward = []
    for module, path in modules():
        if module in ("crchfl_sumo", "crchfl_sumo.cli"):  # the command line reads the package's __version__
            continue
        own = layer_of(module)
        for target in imported_modules(path):
            if target == "crchfl_sumo" or layer_of(target) > own:
                upward.append(f"{module} imports {target}")
    assert upward == []


def test_the_check_sees_an_upward_import(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from crchfl_sumo.studies.report import write_report\n")
    assert imported_modules(bad) == {"crchfl_sumo.studies.report"}
    assert layer_of("crchfl_sumo.studies.report") > layer_of("crchfl_sumo.core.errors")


def test_every_subpackage_says_what_it_is_and_what_it_may_import():
    for name in LAYERS:
        doc = ast.get_docstring(ast.parse((PACKAGE / name / "__init__.py").read_text()))
        assert doc and "May import" in doc, name


def test_no_import_circles():
    graph = {module: {t for t in imported_modules(path) if t != module} for module, path in modules()}
    state: dict[str, str] = {}
    circles = []

    def visit(module: str, stack: list[str]) -> None:
        state[module] = "open"
        for target in sorted(graph.get(module, ())):
            if state.get(target) == "open":
                circles.append(" -> ".join(stack[stack.index(target):] + [target]))
            elif target not in state:
                visit(target, [*stack, target])
        state[module] = "done"

    for module in graph:
        if module not in state:
            visit(module, [module])
    assert circles == []


def test_a_run_config_reads_without_torch():
    # RunConfig is read by many modules and commands: none of them should need torch to reach it
    code = "import sys, crchfl_sumo.federation.run_config; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "False"


# Modules whose configs come with their work: calibration's settings sit beside the training it fits.
CONFIGS_WITH_THEIR_WORK = {"crchfl_sumo.planning.calibration"}


def test_every_config_module_imports_without_torch_or_cvxpy():
    """A config reads (and a run, a reproduction or a sweep is planned) without loading torch or CVXPY:
    every module that defines a ``*Config`` class, in one fresh interpreter."""
    import re
    import subprocess
    import sys

    configs = sorted(
        module for module, path in modules()
        if re.search(r"^class \w+Config\b", path.read_text(), re.M) and module not in CONFIGS_WITH_THEIR_WORK
    )
    assert "crchfl_sumo.federation.run_config" in configs and "crchfl_sumo.studies.reproduce_plan" in configs
    code = "import importlib, sys\n" + "".join(f"importlib.import_module({m!r})\n" for m in configs) + (
        "print(sorted(n for n in ('torch', 'cvxpy') if n in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_no_library_module_imports_a_command_module():
    """A command module (``*_command.py``: what one CLI command does, end to end) is the command line's alone
    (crchfl_sumo.cli and its modules)."""
    offenders = [
        (module, imported) for module, path in modules() if layer_of(module) < LAYERS.index("cli")
        for imported in imported_modules(path) if imported.rsplit(".", 1)[-1].endswith("_command")
    ]
    assert offenders == []
