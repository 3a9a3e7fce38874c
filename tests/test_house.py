"""The house's rules (docs/architecture.md), checked as the next person would: lint and format
(ruff), the layers and no circle of imports (import-linter), the types (mypy), and no source file
too long to hold without a reason stated at its top. Each runs the tool on the whole repository
with the configuration in pyproject.toml, as ``.ci/run`` does through this suite."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The packages, as pyproject.toml installs them: every directory at the top with an __init__.py.
PACKAGES = tuple(sorted(p.parent.name for p in REPO.glob("*/__init__.py")))
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
#: A source file longer than this says at its top why it is one file.
LONGEST = 600
#: The words that start that reason, in the module's docstring.
REASON = "Why one file"


def _tool(*argv: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """Run a tool of this Python's environment in the repository; its output for the message."""
    return subprocess.run(
        [sys.executable, *argv], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


def _explain(result: subprocess.CompletedProcess[str]) -> str:
    return (result.stdout + result.stderr)[-6000:]


def test_ruff_finds_nothing() -> None:
    result = _tool("-m", "ruff", "check", "--no-cache", ".")
    assert result.returncode == 0, _explain(result)


def test_every_file_is_formatted() -> None:
    result = _tool("-m", "ruff", "format", "--check", "--no-cache", ".")
    assert result.returncode == 0, _explain(result)


def test_imports_keep_the_layers_and_make_no_circle() -> None:
    script = "import sys; from importlinter.cli import lint_imports_command; lint_imports_command()"
    result = _tool("-c", script, "--no-cache")
    assert result.returncode == 0, _explain(result)
    assert "0 broken" in result.stdout, _explain(result)


@pytest.mark.slow
def test_the_packages_type_check() -> None:
    result = _tool("-m", "mypy", timeout=900)
    assert result.returncode == 0, _explain(result)
    assert "Success: no issues found" in result.stdout, _explain(result)


def test_every_package_is_installed_checked_and_in_a_layer() -> None:
    linter = PYPROJECT["tool"]["importlinter"]
    contracts = linter["contracts"]
    top = next(c for c in contracts if c["type"] == "layers" and "containers" not in c)
    layered = {name.strip() for layer in top["layers"] for name in layer.split("|")}
    where = {
        "installed (tool.setuptools.packages.find.include)": {
            name.removesuffix("*")
            for name in PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]
        },
        "type-checked (tool.mypy.packages)": set(PYPROJECT["tool"]["mypy"]["packages"]),
        "linted (tool.importlinter.root_packages)": set(linter["root_packages"]),
        "in the packages' layers contract": layered,
    }
    for what, names in where.items():
        assert set(PACKAGES) == names, f"not {what}: {sorted(set(PACKAGES) ^ names)}"


def test_every_package_with_modules_has_its_rooms_layered_exhaustively() -> None:
    contained = {
        container
        for contract in PYPROJECT["tool"]["importlinter"]["contracts"]
        if contract.get("exhaustive")
        for container in contract.get("containers", ())
    }
    packages = set()
    for package in PACKAGES:
        for init in (REPO / package).rglob("__init__.py"):
            directory = init.parent
            rooms = [
                p for p in directory.iterdir() if p.suffix == ".py" and p.name != "__init__.py"
            ]
            rooms += [p for p in directory.iterdir() if (p / "__init__.py").is_file()]
            if len(rooms) > 1:
                packages.add(".".join(directory.relative_to(REPO).parts))
    assert packages <= contained, (
        f"no exhaustive layers contract for {sorted(packages - contained)}"
    )


def test_no_file_too_long_without_a_reason() -> None:
    unexplained = []
    for package in (*PACKAGES, "docs/tools"):
        for path in sorted((REPO / package).rglob("*.py")):
            lines = path.read_text(encoding="utf-8").splitlines()
            if len(lines) > LONGEST and not any(REASON in line for line in lines[:40]):
                unexplained.append(f"{path.relative_to(REPO)} ({len(lines)} lines)")
    assert not unexplained, f"over {LONGEST} lines with no '{REASON} ...' at the top: " + ", ".join(
        unexplained
    )


def test_the_docs_index_lists_every_page() -> None:
    index = (REPO / "docs" / "README.md").read_text(encoding="utf-8")
    pages = sorted(p.name for p in (REPO / "docs").glob("*.md") if p.name != "README.md")
    missing = [page for page in pages if f"]({page})" not in index]
    assert not missing, f"docs/README.md does not list {', '.join(missing)}"


def _modules(package: Path) -> set[str]:
    dotted = ".".join(package.relative_to(REPO).parts)
    names = {p.stem for p in package.glob("*.py") if p.name not in ("__init__.py", "__main__.py")}
    names |= {p.parent.name for p in package.glob("*/__init__.py")}
    return {f"{dotted}.{name}" for name in names}


def test_package_docstrings_name_only_modules_that_exist_and_lists_are_complete() -> None:
    """A package docstring that names modules names existing ones; one that lists them (a
    ``Modules:`` line or a ``* :mod:`` list) lists all of them."""
    import ast
    import re

    problems = []
    for package in PACKAGES:
        for init in sorted((REPO / package).rglob("__init__.py")):
            directory = init.parent
            dotted = ".".join(directory.relative_to(REPO).parts)
            doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))) or ""
            named = {
                f"{dotted}{ref}" if ref.startswith(".") else ref
                for ref in re.findall(r":mod:`~?([\w.]+)`", doc)
            }
            every = {
                name
                for path in REPO.glob("*/")
                if (path / "__init__.py").is_file()
                for name in {path.name} | _all_modules(path)
            }
            missing_targets = sorted(n for n in named if n not in every)
            if missing_targets:
                problems.append(f"{dotted} names no such module: {', '.join(missing_targets)}")
            lists = "Modules:" in doc or re.search(r"^\* :mod:", doc, re.MULTILINE)
            unlisted = sorted(_modules(directory) - named) if lists else []
            if unlisted:
                problems.append(f"{dotted}'s list of modules misses {', '.join(unlisted)}")
    assert not problems, "; ".join(problems)


def _all_modules(package: Path) -> set[str]:
    found = set()
    for init in package.rglob("__init__.py"):
        found |= _modules(init.parent) | {".".join(init.parent.relative_to(REPO).parts)}
    return found
