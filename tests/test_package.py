"""The package works for a user who sets nothing up: a fresh process without the test conftest."""

import ast
import subprocess
import sys
import textwrap
from pathlib import Path


def test_cpu_render_correct_without_manual_warp_config(tmp_path):
    # Tile kernels are wrong on the CPU unless wp.config.enable_cpu_blocks is set: importing
    # rgs_warp must take care of it (it once did not, and CPU renders came out nearly empty).
    code = textwrap.dedent(
        """
        import numpy as np
        from rgs_warp import Camera, GaussianMap, Renderer
        n = 400
        rng = np.random.default_rng(0)
        means = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(2.0, 2.5, n)]
        g = GaussianMap.from_numpy(means, np.tile([0, 0, 0, 1.0], (n, 1)), np.full((n, 3), np.log(0.05)),
                                   np.full(n, 3.0), np.full((n, 9, 3), 0.5), device="cpu")
        tiled = Renderer("cpu").forward(g, Camera(60.0, 60.0, 31.5, 23.5, 64, 48), np.eye(4)).alpha.numpy().copy()
        ref = Renderer("cpu", tiled=False).forward(g, Camera(60.0, 60.0, 31.5, 23.5, 64, 48), np.eye(4)).alpha.numpy()
        assert ref.mean() > 0.3, ref.mean()
        assert np.abs(tiled - ref).max() < 1e-5, np.abs(tiled - ref).max()
        print("ok")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


def test_public_api_imports_without_hidden_ties(tmp_path):
    # the README's entry points come from the package itself, and importing the SLAM does not pull in
    # the evaluation (the application ties the two; the SLAM is usable without it)
    code = textwrap.dedent(
        """
        import sys
        import rgs_warp
        from rgs_warp import SLAM, Camera, Config, Frame, load_config, open_dataset
        assert rgs_warp.SLAM is SLAM and callable(load_config) and callable(open_dataset)
        assert "rgs_warp.eval" not in sys.modules and "rgs_warp.app" not in sys.modules, sorted(sys.modules)
        print("ok")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


# ---- the module graph: the library never imports the application, and no module imports itself back ----
PACKAGE_DIR = Path(__file__).resolve().parents[1] / "src" / "rgs_warp"


def _module_names() -> dict[str, Path]:
    names = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


def _is_main_guard(node: ast.AST) -> bool:
    """``if __name__ == "__main__":``, where a command's entry module imports the application."""
    return isinstance(node, ast.If) and ast.unparse(node.test).replace("'", '"') == '__name__ == "__main__"'


def _imported(tree: ast.AST, package: str) -> list[str]:
    """The dotted names a module imports anywhere (functions included: a deferred import still ties two
    modules), outside its ``__main__`` guard; relative imports made absolute."""
    found, stack = [], [tree]
    while stack:
        node = stack.pop()
        if _is_main_guard(node):
            continue
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            found += [base] + [f"{base}.{alias.name}" for alias in node.names]
        stack.extend(ast.iter_child_nodes(node))
    return found


def import_graph() -> dict[str, set[str]]:
    """rgs_warp's modules and the rgs_warp modules each imports (``from package import submodule``: the
    submodule, not the package's ``__init__``)."""
    modules = _module_names()
    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for imported in _imported(ast.parse(path.read_text(encoding="utf-8")), package):
            if imported in modules:
                targets.add(imported)
            elif imported.rpartition(".")[0] in modules and not imported.startswith(name + "."):
                targets.add(imported.rpartition(".")[0])  # `from module import function`
        targets.discard(name)
        graph[name] = targets
    # `from rgs_warp.x import y` names both rgs_warp.x and rgs_warp.x.y; when y is a submodule the edge is y's
    for targets in graph.values():
        targets -= {t for t in list(targets) if any(other.startswith(t + ".") for other in targets)}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (a path that starts and ends at the same module), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_library_never_imports_the_application():
    graph = import_graph()
    assert {"rgs_warp.slam", "rgs_warp.config"} <= graph["rgs_warp.app.runner"]  # the graph sees imports
    offenders = {
        name: sorted(t for t in targets if t == "rgs_warp.app" or t.startswith("rgs_warp.app."))
        for name, targets in graph.items()
        if not (name == "rgs_warp.app" or name.startswith("rgs_warp.app."))
    }
    assert not {k: v for k, v in offenders.items() if v}, offenders


def test_no_import_cycle_among_the_modules():
    assert find_cycle(import_graph()) is None, " -> ".join(find_cycle(import_graph()))
