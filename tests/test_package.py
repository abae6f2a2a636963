"""The package face: public names load on first use, and the vehicle side imports light."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import perchpose

_HEAVY = ("cv2", "numba", "scipy", "perchpose.estimator", "perchpose.detection.detector")


def _loaded_after(statement: str) -> list[str]:
    probe = f"import sys\n{statement}\nprint(' '.join(m for m in {_HEAVY!r} if m in sys.modules))"
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=120
    )
    return done.stdout.split()


def test_public_names_resolve_to_their_modules() -> None:
    from perchpose.estimator import PerchingEstimator
    from perchpose.values import Estimate

    assert perchpose.PerchingEstimator is PerchingEstimator
    assert perchpose.Estimate is Estimate
    assert set(perchpose.__all__) <= set(dir(perchpose))
    with pytest.raises(AttributeError, match="no attribute 'Detector'"):
        _ = perchpose.Detector  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    "module",
    [
        "perchpose",
        "perchpose.control",
        "perchpose.io.mavlink.link",
        "perchpose.io.mavlink.pilot",
        "perchpose.io.mavlink.landing_target_sink",
        "perchpose.io.crazyflie",
    ],
)
def test_the_controller_and_the_links_import_without_opencv_or_the_pipeline(
    module: str,
) -> None:
    assert _loaded_after(f"import {module}") == []


def test_the_estimator_still_comes_with_the_package_face() -> None:
    assert "perchpose.estimator" in _loaded_after("from perchpose import PerchingEstimator")


def _imports_of(path: Path, modules: dict[str, Path]) -> set[str]:
    """The perchpose modules ``path`` imports, at its top or inside a function."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("perchpose"):
            for alias in node.names:
                child = f"{node.module}.{alias.name}"
                found.add(child if child in modules else str(node.module))
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("perchpose."))
    return found & set(modules)


def test_no_module_imports_one_that_imports_it_back() -> None:
    root = Path(perchpose.__file__).parent
    modules = {}
    for path in root.rglob("*.py"):
        name = ".".join(path.relative_to(root.parent).with_suffix("").parts)
        modules[name.removesuffix(".__init__")] = path
    graph = {name: _imports_of(path, modules) for name, path in modules.items()}
    cycles = []
    for start, imported in graph.items():
        # every module reachable from ``start``; a cycle if ``start`` is among them
        seen: set[str] = set()
        todo = list(imported)
        while todo:
            name = todo.pop()
            if name not in seen:
                seen.add(name)
                todo.extend(graph[name])
        if start in seen:
            cycles.append(start)
    assert cycles == []
