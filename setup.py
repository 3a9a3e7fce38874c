"""The build hook that bakes the source's commit into a built package (docs/fleet.md).

Everything else about the package is in ``pyproject.toml``. A wheel or an sdist gets
``minimize_surprise/_build.py`` holding ``COMMIT``, which the installed agent and master report
(``minimize_surprise.provenance``). The commit comes from ``MINIMIZE_SURPRISE_COMMIT`` when set
(``deploy/install-pi.sh`` sets it: it builds from a copy without ``.git``), else from git in the
source tree, else from a ``_build.py`` already in the source (a wheel built from an sdist), else
it stays unknown. An editable install gets no file: the package then asks git itself.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.command.sdist import sdist

#: The generated module, relative to a tree holding the packages.
BUILD_MODULE = Path("minimize_surprise") / "_build.py"
#: Set to a commit (40 or 64 hex digits, maybe ``-dirty``) to bake that one in.
COMMIT_ENV = "MINIMIZE_SURPRISE_COMMIT"
_COMMIT_RE = re.compile(r"^[0-9a-f]{40}([0-9a-f]{24})?(-dirty)?$")
_STAMPED_RE = re.compile(r'^COMMIT = "([0-9a-z-]+)"$', re.M)


def source_commit(source: Path) -> str | None:
    """The commit to bake in for the tree ``source`` (see the module docstring)."""
    given = os.environ.get(COMMIT_ENV, "").strip()
    if given:
        if not _COMMIT_RE.match(given):
            raise SystemExit(f"{COMMIT_ENV}={given!r} is not a commit (40 hex digits[-dirty])")
        return given
    if (source / ".git").exists():
        git = ["git", "-c", f"safe.directory={source}", "-C", str(source)]
        try:
            head = subprocess.run(
                [*git, "rev-parse", "--verify", "HEAD"], capture_output=True, text=True, timeout=10
            )
            if head.returncode == 0 and _COMMIT_RE.match(head.stdout.strip()):
                diff = subprocess.run(
                    [*git, "diff", "--quiet", "HEAD", "--"], capture_output=True, timeout=10
                )
                return head.stdout.strip() + ("-dirty" if diff.returncode == 1 else "")
        except (OSError, subprocess.TimeoutExpired):
            pass
    stamped = source / BUILD_MODULE
    if stamped.is_file():
        found = _STAMPED_RE.search(stamped.read_text(encoding="utf-8"))
        if found and _COMMIT_RE.match(found.group(1)):
            return found.group(1)
    return None


def stamp(tree: Path, commit: str | None) -> None:
    """Write the generated module into ``tree`` (a build or release directory)."""
    path = tree / BUILD_MODULE
    path.parent.mkdir(parents=True, exist_ok=True)
    value = "None" if commit is None else f'"{commit}"'
    path.write_text(
        '"""Generated when this package was built (setup.py); not in the source."""\n\n'
        f"COMMIT = {value}\n",
        encoding="utf-8",
    )


class BuildPyWithCommit(build_py):
    """``build_py`` that also writes ``_build.py`` into the build (not for editable installs)."""

    def run(self) -> None:
        super().run()
        if not self.editable_mode:
            stamp(Path(self.build_lib), source_commit(Path.cwd()))


class SdistWithCommit(sdist):
    """``sdist`` that puts ``_build.py`` into the archive, for the wheel built from it."""

    def make_release_tree(self, base_dir: str, files: list[str]) -> None:
        super().make_release_tree(base_dir, files)
        stamp(Path(base_dir), source_commit(Path.cwd()))


if __name__ == "__main__":
    setup(cmdclass={"build_py": BuildPyWithCommit, "sdist": SdistWithCommit})
