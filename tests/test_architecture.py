"""The package's shape: the documented module graph is current, the GICP core and the entry
points load only what they need, modules stay readable, and the public API resolves."""

import importlib
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

import gloam_jax

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"


def _loaded_after(statement: str) -> set[str]:
    """Top-level names of the modules that ``statement`` leaves loaded in a fresh Python."""
    code = f"import sys\n{statement}\nprint('\\n'.join(sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_module_graph_in_the_docs_is_current():
    spec = importlib.util.spec_from_file_location("module_graph", ROOT / "scripts/module_graph.py")
    graph = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(graph)
    text = DOC.read_text()
    assert graph.replace_block(text, graph.mermaid()) == text, "run module_graph.py --write"
    # The registration core sits below the learned parts and the model file.
    assert not {e for e in graph.edges() if e[0] == "gicp"} - {
        ("gicp", "association"),
        ("gicp", "geometry"),
    }


def test_names_in_the_architecture_doc_exist():
    text = DOC.read_text()
    names = set(re.findall(r"`(gloam_jax(?:\.\w+)+)`", text))
    for label in re.findall(r"<br/>([^\"]+)\"", text):
        first, *rest = (s.strip() for s in label.split(","))
        names.add(f"gloam_jax.{first}")
        # "features.get_backbone, FeaturePCA": a bare name lives in the first one's module
        module = first.split(".")[0]
        names.update(f"gloam_jax.{r}" if "." in r else f"gloam_jax.{module}.{r}" for r in rest)
    assert len(names) > 20
    for name in sorted(names):
        parts = name.split(".")
        for i in range(len(parts), 0, -1):  # the longest importable prefix, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ModuleNotFoundError:
                continue
            for attr in parts[i:]:
                assert hasattr(obj, attr), name
                obj = getattr(obj, attr)
            break
        else:
            pytest.fail(f"{name} does not exist")


def test_the_gicp_core_loads_no_model_backbone_or_training_code():
    loaded = _loaded_after("import gloam_jax.gicp")
    banned = {"sklearn", "optuna", "matplotlib", "gloam_jax.models", "gloam_jax.features",
              "gloam_jax.learned", "gloam_jax.training"}  # fmt: skip
    assert not {m for m in loaded if m.split(".")[0] in banned or m in banned}


def test_the_package_and_the_cli_load_without_jax():
    for statement in ("import gloam_jax", "import gloam_jax.cli"):
        loaded = _loaded_after(statement)
        assert not loaded & {"jax", "sklearn", "optuna", "scipy"}, statement


def test_public_api_resolves():
    assert {"align", "Odometry", "GICPConfig", "load_model"} <= set(gloam_jax.__all__)
    for name in gloam_jax.__all__:
        assert getattr(gloam_jax, name) is not None
    assert gloam_jax.align is importlib.import_module("gloam_jax.registration").align
    with pytest.raises(AttributeError):
        gloam_jax.no_such_name  # noqa: B018


def test_no_module_is_longer_than_600_lines():
    lengths = {p: len(p.read_text().splitlines()) for p in (ROOT / "gloam_jax").rglob("*.py")}
    assert max(lengths.values()) <= 600, max(lengths, key=lengths.get)


def _module_level_imports(path: Path) -> set[str]:
    """The gloam_jax modules that ``path`` imports at module level, ``if TYPE_CHECKING:`` blocks
    included (an annotation-only import is still a dependency a reader follows)."""
    import ast

    names, body = set(), list(ast.parse(path.read_text()).body)
    while body:
        node = body.pop()
        if isinstance(node, ast.If | ast.Try):
            body += node.body + node.orelse
        elif isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.update(f"{node.module}.{a.name}" for a in node.names)
            names.add(node.module)
    return {n for n in names if n.startswith("gloam_jax")}


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Each cycle of ``edges`` as the path that closes it (depth first)."""
    found, state = [], {}

    def visit(node, path):
        state[node] = "open"
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                found.append(path[path.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    return found


def test_no_import_cycle():
    root = Path(gloam_jax.__file__).parent
    files = {}
    for path in root.rglob("*.py"):
        parts = path.relative_to(root.parent).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    # A package's __init__ always loads before its modules: an import of an ancestor package
    # (``from gloam_jax import io``) is not an edge back to it.
    edges = {
        name: {
            m
            for m in _module_level_imports(path) & files.keys()
            if not f"{name}.".startswith(f"{m}.")
        }
        for name, path in files.items()
    }
    assert _cycles(edges) == []
    # the check sees a cycle where there is one
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
