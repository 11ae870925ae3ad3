"""The package's module graph, read from the source: which module imports which at load time.

Prints a Mermaid flowchart (GitHub renders it) of the imports between ``gloam_jax`` modules that
run when a module is imported (module level, outside ``if TYPE_CHECKING``); imports inside
functions are the lazy ones and are left out. The ``io``, ``features`` and ``simulate``
packages are drawn as one node each. ``--check docs/architecture.md`` exits 1 when the graph
in that file is not the current one; ``--write`` replaces it.

    python scripts/module_graph.py                      # print the graph
    python scripts/module_graph.py --write docs/architecture.md
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "gloam_jax"
COLLAPSED = ("io", "features", "simulate")  # subpackages drawn as one node
BEGIN, END = "<!-- module-graph:begin -->", "<!-- module-graph:end -->"


def node(module: str) -> str:
    """``gloam_jax.io.kitti`` -> ``io``; ``gloam_jax.training.grad`` -> ``training.grad``."""
    parts = module.split(".")[1:]
    if parts and parts[0] in COLLAPSED:
        return parts[0]
    return ".".join(p for p in parts if p != "__init__") or "gloam_jax"


def _type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def load_time_imports(path: Path, module: str) -> set[str]:
    """The gloam_jax modules that importing ``module`` (its file ``path``) imports."""
    found: set[str] = set()

    def visit(body: list[ast.stmt]) -> None:
        for stmt in body:
            if isinstance(stmt, ast.Import):
                found.update(a.name for a in stmt.names if a.name.startswith("gloam_jax"))
            elif isinstance(stmt, ast.ImportFrom) and stmt.module:
                if stmt.level:  # relative: resolve against the package
                    base = module.split(".")[: -stmt.level]
                    name = ".".join([*base, stmt.module])
                else:
                    name = stmt.module
                if not name.startswith("gloam_jax"):
                    continue
                # "from gloam_jax import io" names a module; "from gloam_jax.x import f" does not
                for a in stmt.names:
                    sub = f"{name}.{a.name}"
                    is_module = (PACKAGE.parent / (sub.replace(".", "/") + ".py")).is_file() or (
                        PACKAGE.parent / sub.replace(".", "/")
                    ).is_dir()
                    found.add(sub if is_module else name)
            elif isinstance(stmt, ast.If) and not _type_checking(stmt.test):
                visit(stmt.body)
                visit(stmt.orelse)
            elif isinstance(stmt, ast.Try):
                visit(stmt.body)

    visit(ast.parse(path.read_text()).body)
    return found


def edges() -> set[tuple[str, str]]:
    out = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        for target in load_time_imports(path, module):
            a, b = node(module), node(target)
            if a != b and b not in ("errors", "gloam_jax"):  # errors: imported by nearly all
                out.add((a, b))
    return out


def mermaid() -> str:
    lines = ["```mermaid", "flowchart LR"]
    lines += [f"  {a.replace('.', '_')}[{a}] --> {b.replace('.', '_')}[{b}]"
              for a, b in sorted(edges())]  # fmt: skip
    lines.append("```")
    return "\n".join(lines)


def replace_block(text: str, block: str) -> str:
    if BEGIN not in text or END not in text:
        raise SystemExit(f"the file has no {BEGIN} ... {END} block")
    head, rest = text.split(BEGIN, 1)
    return f"{head}{BEGIN}\n{block}\n{END}{rest.split(END, 1)[1]}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--check", type=Path, help="exit 1 if this file's graph is stale")
    group.add_argument("--write", type=Path, help="replace this file's graph")
    args = parser.parse_args()
    block = mermaid()
    if args.check is not None:
        text = args.check.read_text()
        if replace_block(text, block) != text:
            print(f"{args.check}: the module graph is stale; run with --write", file=sys.stderr)
            raise SystemExit(1)
    elif args.write is not None:
        args.write.write_text(replace_block(args.write.read_text(), block))
    else:
        print(block)


if __name__ == "__main__":
    main()
