"""No module imports one above it.

robot <- closed loop <- methods <- detection <- evaluation <- apps.

The layers are read from the folders; every ``import`` and ``from ... import``
in every module (function-level ones too) is checked.
"""

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "src" / "rmijax"

LAYERS = {
    "rmijax._checks": 0,
    "rmijax._linalg": 0,
    "rmijax._intervals": 0,
    "rmijax._affine": 0,
    "rmijax.robots": 1,
    "rmijax.control": 2,
    "rmijax.trajectory": 2,
    "rmijax.plant": 2,
    "rmijax.methods": 3,
    "rmijax.detection": 4,
    "rmijax.evaluation": 5,
    "rmijax.io": 5,
    "rmijax.fleet": 5,
    "rmijax.apps": 6,
    "rmijax": 7,  # the package's __init__ re-exports everything
}


def layer_of(module: str) -> int:
    """The layer of a dotted module name: its longest prefix in LAYERS."""
    parts = module.split(".")
    for cut in range(len(parts), 0, -1):
        name = ".".join(parts[:cut])
        if name in LAYERS:
            return LAYERS[name]
    raise KeyError(f"{module} belongs to no layer; add it to LAYERS in {__file__}")


def module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, module: str, is_package: bool):
    """Every rmijax module ``source`` imports, as dotted names (with line numbers)."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "rmijax":
                    yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "rmijax":
                continue
            for alias in node.names:  # `from rmijax.methods import rmi` names a module
                candidate = f"{target}.{alias.name}"
                sub = PACKAGE.parent / pathlib.Path(*candidate.split("."))
                is_module = sub.with_suffix(".py").exists() or sub.is_dir()
                yield (candidate if is_module else target), node.lineno


def violations(source: str, module: str, is_package: bool = False):
    mine = layer_of(module)
    return [
        f"{module} (layer {mine}) imports {target} (layer {layer_of(target)}) at line {line}"
        for target, line in imported_modules(source, module, is_package)
        if layer_of(target) > mine
    ]


def test_no_module_imports_a_higher_layer():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = module_name(path)
        found += violations(path.read_text(), module, path.name == "__init__.py")
    assert not found, "\n".join(found)


def test_every_module_has_a_layer():
    for path in PACKAGE.rglob("*.py"):
        layer_of(module_name(path))


@pytest.mark.parametrize(
    "source, module",
    [
        ("from rmijax.methods.rmi import rmi\n", "rmijax.robots.box"),
        ("def f():\n    from rmijax.apps import experiments\n", "rmijax.methods.dispatch"),
        ("import rmijax.detection.detect\n", "rmijax.plant"),
        ("from ..evaluation import worst_case\n", "rmijax.detection.monitor"),
    ],
)
def test_the_check_catches_an_upward_import(source, module):
    assert violations(source, module)


def test_the_check_allows_downward_and_sideways_imports():
    assert not violations("from rmijax.robots.box import UncertainRobot\n", "rmijax.methods.rmi")
    assert not violations("from rmijax.control import servo_command\n", "rmijax.trajectory")
    assert not violations("from rmijax import _checks\n", "rmijax.robots.box")
