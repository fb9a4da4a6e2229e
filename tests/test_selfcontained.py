"""The repository is self-contained: no tracked file points at a file a user's clone does not have."""

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Written in pieces so that this file does not match its own patterns.
PARENT = re.compile(r"(?<![\w./])\.\./[\w.-][\w./-]*")
ABSOLUTE = re.compile(r"(?<![\w.~])/(?:" + "work|home|Users|" + "root)/")
FOREIGN_NAMES = ("PHYSICS" + ".md", "HELPER" + "_BRIEF", "seed" + "/000_")
MARKDOWN_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def _tracked_text_files():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: the tracked files are unknown")
    names = subprocess.run(["git", "-C", str(ROOT), "ls-files"], capture_output=True, text=True,
                           check=True).stdout.splitlines()
    for name in names:
        path = ROOT / name
        if not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data:
            continue                                   # binary (an MCAP test file)
        yield name, path, data.decode("utf-8", errors="replace")


def outside_references(name, path, text):
    """The references in one file's text that leave the repository or name a file it does not hold."""
    found = []
    for match in PARENT.finditer(text):
        target = (path.parent / match.group(0)).resolve()
        if not target.is_relative_to(ROOT):
            found.append(match.group(0))
    found += [match.group(0) for match in ABSOLUTE.finditer(text)]
    found += [foreign for foreign in FOREIGN_NAMES if foreign in text]
    if name.endswith(".md"):
        for match in MARKDOWN_LINK.finditer(text):
            link = match.group(1)
            if "://" in link or link.startswith("mailto:"):
                continue
            target = (path.parent / link).resolve()
            if not target.is_relative_to(ROOT) or not target.exists():
                found.append(link)
    return found


def test_no_tracked_file_references_a_path_outside_the_repository():
    offences = {name: refs for name, path, text in _tracked_text_files()
                if (refs := outside_references(name, path, text))}
    assert offences == {}


@pytest.mark.parametrize("text", ["see .." + "/shared/notes.md", "in /wo" + "rk/main/x",
                                  "decision 1 of PHYSICS" + ".md", "[physics](docs/missing.md)",
                                  "[up](.." + "/../README.md)"])
def test_the_check_catches_an_outside_reference(text):
    assert outside_references("README.md", ROOT / "README.md", text)


@pytest.mark.parametrize("name, text", [("README.md", "see docs/physics.md"),
                                        ("README.md", "[physics](docs/physics.md#saw-models)"),
                                        ("README.md", "[site](https://example.org/a/../b)"),
                                        ("tests/test_x.py", 'scenario = "../empty.toml"')])
def test_the_check_accepts_references_inside_the_repository(name, text):
    assert outside_references(name, ROOT / name, text) == []
