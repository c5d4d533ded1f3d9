"""MkDocs hooks: a method page's table of config keys, read from the method's ``DEFAULT_CONFIG``;
and docstring brackets that are not links.

A page that holds the line ``<!-- config-keys: rrf -->`` gets, in its place, a table of every key
of ``jprt/methods/rrf/*.py``'s ``DEFAULT_CONFIG`` (dotted), its default as written in the source,
and the comments written beside or above it. The source is parsed, not imported, so the table is
what the code says at build time and the build needs neither JAX nor Mitsuba.

Docstrings write indexed operators as ``R[type][side]``, which Markdown reads as a reference link;
autorefs warns that it finds no target. Such warnings from a docstring under ``jprt/`` are logged
at INFO (the text is rendered as written); unresolved links in the docs' own pages still fail
``mkdocs build --strict``.
"""

from __future__ import annotations

import ast
import glob
import io
import logging
import os
import re
import tokenize

from mkdocs.exceptions import PluginError

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
MARKER = re.compile(r"^<!-- config-keys: ([a-z_]+) -->$", re.M)


def _find(method: str):
    """(path, source, the dict node) of the method package's top-level ``DEFAULT_CONFIG``."""
    for path in sorted(glob.glob(os.path.join(ROOT, "jprt", "methods", method, "*.py"))):
        with open(path, encoding="utf-8") as f:
            src = f.read()
        for node in ast.parse(src).body:
            target = node.targets[0] if isinstance(node, ast.Assign) else getattr(node, "target", None)
            if isinstance(target, ast.Name) and target.id == "DEFAULT_CONFIG" and isinstance(node.value, ast.Dict):
                return path, src, node.value
    raise PluginError(f"config-keys: no DEFAULT_CONFIG dict literal in jprt/methods/{method}/*.py")


def _comments(src: str) -> dict[int, tuple[str, bool]]:
    """Line -> (comment text, whether the comment is the whole line)."""
    out = {}
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = (tok.string.lstrip("#").strip(), tok.line[:tok.start[1]].strip() == "")
    return out


def rows(method: str) -> tuple[str, list[tuple[str, str, str]]]:
    """The source file and (dotted key, default, comment) of every key, sections included."""
    path, src, root = _find(method)
    comments = _comments(src)
    lines = src.splitlines()
    out = []
    used: set[int] = set()  # comment lines already given to a key (a one-line section's comment)

    def above(lineno: int) -> list[str]:
        got, ln = [], lineno - 1
        while ln in comments and comments[ln][1]:
            got.insert(0, comments[ln][0])
            ln -= 1
        return got

    def walk(node: ast.Dict, prefix: str):
        for i, (k, v) in enumerate(zip(node.keys, node.values)):
            if k is None:  # ** expansion
                out.append((f"{prefix}**", ast.get_source_segment(src, v) or "", ""))
                continue
            key = prefix + str(ast.literal_eval(k)) if isinstance(k, ast.Constant) else prefix + (ast.get_source_segment(src, k) or "?")
            first_on_line = lines[k.lineno - 1][:k.col_offset].strip() in ("", "{")
            notes = above(k.lineno) if first_on_line else []
            last_on_line = i + 1 == len(node.keys) or node.keys[i + 1] is None or node.keys[i + 1].lineno != v.end_lineno
            trailing = comments.get(v.end_lineno)
            if trailing and not trailing[1] and last_on_line and v.end_lineno not in used \
                    and not (isinstance(v, ast.Dict) and v.lineno != v.end_lineno):
                notes.append(trailing[0])
                used.add(v.end_lineno)
            if isinstance(v, ast.Dict) and v.keys:
                if notes:
                    out.append((key, "(section)", " ".join(notes)))
                walk(v, key + ".")
            else:
                out.append((key, ast.get_source_segment(src, v) or "", " ".join(notes)))

    walk(root, "")
    return os.path.relpath(path, ROOT), out


def _cell(s: str) -> str:
    return " ".join(s.split()).replace("|", "\\|")


def _code(s: str) -> str:
    s = " ".join(s.split())
    return "`` " + s.replace("|", "\\|") + " ``" if "`" in s else "`" + s.replace("|", "\\|") + "`"


def table(method: str) -> str:
    path, got = rows(method)
    lines = [f"Every key of `DEFAULT_CONFIG` in `{path}`, read from the source when this site was built; "
             "the notes are the comments written beside each key.", "",
             "| key | default | notes |", "|---|---|---|"]
    for key, default, note in got:
        lines.append(f"| `{key}` | {'section' if default == '(section)' else _code(default)} | {_cell(note)} |")
    return "\n".join(lines) + "\n"


def on_page_markdown(markdown, page, config, files):  # noqa: ARG001 (the hook's signature)
    return MARKER.sub(lambda m: table(m.group(1)), markdown)


class _DocstringBrackets(logging.Filter):
    """Downgrades autorefs' "Could not find cross-reference target" when it comes from a jprt docstring."""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if record.levelno == logging.WARNING and "Could not find cross-reference target" in msg \
                and f"from {os.path.join(ROOT, 'jprt')}" in msg:
            record.levelno, record.levelname = logging.INFO, "INFO"
        return True


def on_config(config):
    logger = logging.getLogger("mkdocs.plugins.mkdocs_autorefs._internal.plugin")
    if not any(isinstance(f, _DocstringBrackets) for f in logger.filters):
        logger.addFilter(_DocstringBrackets())
    return config
