"""The repository stands alone: version, licence, bundled data and documents it cites."""

import importlib.metadata
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import tawarp
from tawarp.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_version_is_the_one_of_pyproject(capsys):
    """``tawarp --version`` prints the installed distribution's version, which is
    pyproject.toml's and ``tawarp.__version__``; argparse exits 0."""
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert capsys.readouterr().out.strip() == f"tawarp {declared}"
    assert importlib.metadata.version("tawarp") == tawarp.__version__ == declared


def test_licence_file_is_the_declared_one():
    """pyproject declares MIT (an SPDX expression, with the file it ships); the LICENSE
    file is the MIT text."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "Permission is hereby granted, free of charge" in text


def _documents():
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "bench").glob("*.md"))]


def _anchors(doc: Path) -> set[str]:
    """GitHub's anchors of a Markdown file's headings (lower case, punctuation dropped,
    blanks as hyphens)."""
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
    return {
        re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in re.findall(r"^#+ (.+)$", text, flags=re.M)
    }


def test_documents_cite_only_files_of_the_repository():
    """Every relative Markdown link of the README, docs/ and bench/ resolves inside the
    repository, to a heading where it names one, and nothing points at a folder beside
    the clone (``../shared``)."""
    for doc in _documents():
        text = doc.read_text()
        assert "../shared" not in text, doc
        for target, anchor in re.findall(r"\]\(([^)#\s]*)(?:#([^)\s]*))?\)", text):
            if "://" in target:
                continue
            path = (doc.parent / target).resolve() if target else doc
            where = f"{doc.relative_to(ROOT)}: link {target}#{anchor}"
            assert path.exists() and (path == doc or ROOT in path.parents), where + " does not resolve"
            if anchor and path.suffix == ".md":
                assert anchor in _anchors(path), where + ": no such heading"


def test_physics_and_formats_contract_are_in_docs():
    """The physics and the formats contract are documents of the repository, and the
    measured CSV's columns are defined there."""
    formats = (ROOT / "docs" / "formats.md").read_text()
    for column in ("Q_W", "freq_Hz", "Tpp_re", "Tuu_im", "sigma_Tpp", "Zs_re", "S11_re"):
        assert column in formats
    assert "exp(-iwt)" in formats and "volume velocity" in formats
    physics = (ROOT / "docs" / "physics.md").read_text()
    assert "Checks any implementation must pass" in physics


def test_ruff_check_is_clean():
    """``ruff check .`` with pyproject.toml's rule set finds nothing (ruff is in the test extra)."""
    done = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", str(ROOT)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_ruff_format_is_clean():
    """``ruff format --check .`` finds nothing to reformat (pyproject.toml's [tool.ruff.format])."""
    done = subprocess.run(
        [sys.executable, "-m", "ruff", "format", "--check", "--no-cache", str(ROOT)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_kernels_write_no_float32_quotient_as_float64():
    """In a Warp function ``wp.float64(1.0 / 60.0)`` divides two float32 literals (1e-8
    relative) before the conversion: the kernels write such constants as module-level
    ``wp.constant`` values (a Python float64) instead."""
    quotient = re.compile(r"wp\.float64\(\s*-?[0-9.]+\s*/\s*[0-9.]+\s*\)")
    offenders = [
        f"{path.name}:{n}"
        for path in sorted((ROOT / "kernels").glob("*.py"))
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if quotient.search(line) and not line.lstrip().startswith("#") and "wp.constant(" not in line
    ]
    assert not offenders, f"float32 quotients in float64 constants at {offenders}"
