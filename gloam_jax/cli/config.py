"""``gloam config dump``: a method's settings as commented YAML; and the settings' documentation
read from the dataclasses themselves (their field comments), so it cannot drift from them.

Each field's meaning is the comment on its line, or the comment lines just above it, in the
class's source; its unit is the comment's leading unit (``m; ...``), a ``(unit)`` in it, or
the name's ``_deg`` ending.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import textwrap
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, Literal, Union, get_args, get_origin, get_type_hints

import typer

from gloam_jax.cli.common import app, console, user_errors

config_app = typer.Typer(help="Settings files: write a method's settings, commented.")
app.add_typer(config_app, name="config")

_UNITS = ("m/s", "ms", "m", "s", "rad", "deg", "Hz", "%")
_ALTERNATIVES = "|".join(re.escape(u) for u in _UNITS)
_LEADING = re.compile(rf"^({_ALTERNATIVES})(?=[;,:]|\s|$)")
_INSIDE = re.compile(rf"\(({_ALTERNATIVES})\)")


def field_comments(cls: type) -> dict[str, str]:
    """``{field: comment}`` of a dataclass, from its source: the comment after the field on
    its line, else the comment lines right above it (joined); fields without one are left out."""
    lines, _ = inspect.getsourcelines(cls)
    tree = ast.parse(textwrap.dedent("".join(lines)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    out: dict[str, str] = {}
    for node in body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        row = node.lineno - 1
        comments = []
        for line in lines[node.lineno - 1 : node.end_lineno]:
            tail = _comment(line)
            if tail:
                comments.append(tail)
        above = []
        k = row - 1
        while k >= 0 and lines[k].strip().startswith("#"):
            above.insert(0, lines[k].strip().lstrip("#").strip())
            k -= 1
        text = " ".join(above + comments).strip()
        if text:
            out[node.target.id] = text
    return out


def _comment(line: str) -> str:
    """The ``# comment`` at the end of a code line (outside strings), without ``fmt:`` pragmas."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#":
            text = line[i + 1 :].strip()
            return "" if text.startswith(("fmt:", "noqa", "type:")) else text
    return ""


def unit_of(name: str, comment: str) -> str:
    match = _LEADING.match(comment) or _INSIDE.search(comment)
    if match:
        return match.group(1)
    return "deg" if name.endswith("_deg") else ""


def _type_name(hint: Any) -> str:
    """A type as a reader would write it: ``float``, ``int | null``, ``plane | raw_eps``."""
    origin, args = get_origin(hint), get_args(hint)
    if hint is type(None):
        return "null"
    if origin is Literal:
        return " | ".join(str(a) for a in args)
    if origin in (Union, UnionType):
        return " | ".join(_type_name(a) for a in args)
    if origin is tuple:
        return f"list of {_type_name(args[0])}"
    return getattr(hint, "__name__", str(hint))


def setting_rows(cls: type, prefix: str = "") -> list[dict[str, str]]:
    """One row per setting of ``cls`` (nested sections flattened as ``section.field``):
    name, type, default, unit and meaning."""
    comments = field_comments(cls)
    hints = get_type_hints(cls)
    default = cls()
    rows: list[dict[str, str]] = []
    for f in dataclasses.fields(cls):
        value = getattr(default, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            rows.extend(setting_rows(hints[f.name], f"{prefix}{f.name}."))
            continue
        comment = comments.get(f.name, "")
        rows.append({
            "name": f"{prefix}{f.name}",
            "type": _type_name(hints[f.name]),
            "default": _yaml_value(value),
            "unit": unit_of(f.name, comment),
            "meaning": comment,
        })  # fmt: skip
    return rows


def _yaml_value(value: Any) -> str:
    """One value as YAML flow text: strings quoted only where YAML needs it, the rest as JSON
    (valid YAML: ``null``, ``true``, ``["01", "03"]``)."""
    import json

    import yaml

    if isinstance(value, str):
        return yaml.safe_dump(value, default_flow_style=True).removesuffix("\n...\n").strip()
    return json.dumps(list(value) if isinstance(value, tuple) else value)


def commented_yaml(config: Any, header: str = "") -> str:
    """``config`` (a settings dataclass) as YAML with each field's comment above it."""
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    _emit(config, 0, lines)
    return "\n".join(lines) + "\n"


def _emit(config: Any, depth: int, lines: list[str]) -> None:
    comments = field_comments(type(config))
    pad = "  " * depth
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        for line in textwrap.wrap(comments.get(f.name, ""), 96 - len(pad)):
            lines.append(f"{pad}# {line}")
        if dataclasses.is_dataclass(value):
            lines.append(f"{pad}{f.name}:")
            _emit(value, depth + 1, lines)
        else:
            lines.append(f"{pad}{f.name}: {_yaml_value(value)}")


@config_app.command(
    "dump",
    epilog="Examples:\n\n  gloam config dump gloam > my_gloam.yaml\n\n"
    "  gloam config dump gicp --out configs/mine.yaml\n\n  gloam config dump train_grad",
)
@user_errors
def dump(
    method: Annotated[
        str,
        typer.Argument(
            help="A shipped config (gicp, gicp_da, gicp_ce, gloam, train_grad, ...) or a file."
        ),
    ],
    out: Annotated[Path | None, typer.Option(help="Write here instead of printing.")] = None,
) -> None:
    """Write a method's settings as YAML, every setting with its meaning; edit it and pass it
    back with ``gloam run --config FILE``."""
    from gloam_jax.config import load_config, resolve_config
    from gloam_jax.io import write_atomic
    from gloam_jax.odometry import OdometryConfig
    from gloam_jax.training.config import TrainConfig

    path = resolve_config(method)
    cls = TrainConfig if path.stem.startswith("train") else OdometryConfig
    config = load_config(path, cls)
    header = (
        f"gloam-jax settings: {path.stem} (fields of {cls.__module__}.{cls.__qualname__})\n"
        "every setting with its meaning; docs/config.md lists units and defaults"
    )
    text = commented_yaml(config, header)
    if out is None:
        console.print(text, end="", markup=False, highlight=False, soft_wrap=True)
    else:
        write_atomic(out, text)
        console.print(f"wrote {out}")
