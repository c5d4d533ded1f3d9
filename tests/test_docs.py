"""The documentation: the MkDocs site builds with --strict, every generated benchmark page is what
its JSON renders to now, the README stays a short user's guide and its relative links resolve."""

import importlib.util
import os
import re
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _docs_pages():
    spec = importlib.util.spec_from_file_location("docs_pages", os.path.join(ROOT, "benchmarks", "docs_pages.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_mkdocs_build_strict(tmp_path):
    missing = [m for m in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")
               if importlib.util.find_spec(m.split(".")[0]) is None or importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"the docs' packages are not installed ({', '.join(missing)}): pip install -e '.[docs]'")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    warnings = [line for line in (proc.stdout + proc.stderr).splitlines() if "WARNING" in line or "ERROR" in line]
    assert proc.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(warnings or [proc.stderr[-3000:]])
    assert (tmp_path / "site" / "index.html").exists()


def test_benchmark_pages_match_their_json():
    bad = _docs_pages().differences()
    assert not bad, ("docs/benchmarks/ disagrees with benchmarks/results/*.json; run "
                     "`python benchmarks/docs_pages.py`:\n" + "\n".join(bad))


def test_a_page_that_disagrees_with_its_json_is_caught(tmp_path):
    mod = _docs_pages()
    pages = mod.pages()
    for name, content in pages.items():
        mode = "wb" if isinstance(content, bytes) else "w"
        with open(tmp_path / name, mode) as f:
            f.write(content)
    assert mod.differences(str(tmp_path)) == []
    name = next(n for n in pages if n.endswith(".md") and n != "index.md")
    (tmp_path / name).write_text(pages[name].replace("|", "| 1", 1))
    assert mod.differences(str(tmp_path)) == [f"{name}: differs from what its JSON renders to"]


def test_readme_is_short():
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        n = len(f.read().splitlines())
    assert n < 300, f"README.md has {n} lines; it is a user's guide (the rest belongs in docs/ or CHANGELOG.md)"


def test_readme_relative_links_exist():
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        text = f.read()
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # code blocks hold no links
    targets = re.findall(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", text)
    relative = [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:", t) and not t.startswith("#")]
    assert relative, "no relative links found in README.md"
    missing = [t for t in relative if not os.path.exists(os.path.join(ROOT, t.split("#")[0]))]
    assert not missing, f"README.md links to files that do not exist: {missing}"
