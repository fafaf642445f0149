"""The package's imports go one way: core modules, then filters, then training, then the shipped
models, then the package's ``__init__`` (README, "Layout"). A module may import its own layer or
any layer below it, never one above, and nothing in the package imports ``experiments``."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "csf_jax"
LAYERS = {"filters": 1, "methods": 1, "fit": 2, "training": 2, "pretrained": 3, "__init__": 4}


def _layer(module: str) -> int:
    """``csf_jax.filters.csf`` and ``csf_jax.methods`` (the filters' registry) -> 1; core modules
    (``ssm``, ``prior``, ``problems``, ...) -> 0."""
    parts = module.split(".")[1:]
    if not parts:
        return LAYERS["__init__"]
    return LAYERS.get(parts[0], 0)


def _modules():
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        name = ".".join(rel.parts)
        if name.endswith(".__init__"):
            name = name[: -len(".__init__")]
        yield name, path


def _imports(path: pathlib.Path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # `from csf_jax import networks` imports the submodule, not the package's __init__
            if node.module == "csf_jax":
                yield from (f"csf_jax.{a.name}" for a in node.names)
            else:
                yield node.module


@pytest.mark.parametrize("name, path", list(_modules()), ids=lambda v: str(v))
def test_imports_go_one_way(name, path):
    # a package's __init__ re-exports its own layer: it counts as that layer
    own = LAYERS["__init__"] if name == "csf_jax" else _layer(name)
    for target in _imports(path):
        assert not target.startswith("experiments"), f"{name} imports {target}"
        if not target.startswith("csf_jax"):
            continue
        if target == "csf_jax":
            assert own == LAYERS["__init__"], f"{name} imports the package's __init__"
            continue
        head = ".".join(target.split(".")[:2])  # csf_jax.<top-level module or subpackage>
        assert _layer(head) <= own, f"{name} (layer {own}) imports {target} (layer {_layer(head)})"


def test_the_check_catches_a_back_edge(tmp_path):
    """A filter importing the training package is what the check refuses."""
    src = tmp_path / "bad.py"
    src.write_text("from csf_jax.training.train import TrainConfig\n")
    targets = list(_imports(src))
    assert any(_layer(".".join(t.split(".")[:2])) > _layer("csf_jax.filters.sf") for t in targets)
