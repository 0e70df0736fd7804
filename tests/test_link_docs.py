"""Every reference to a file under docs/ in the repository's code and documentation resolves to a file.

A reference is ``docs/<path>`` in any tracked text file (code, comments, READMEs, TOML), and a relative
Markdown link inside docs/ itself. (The file is named test_link_* because it checks links.)
"""

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TEXT_SUFFIXES = {".py", ".md", ".toml", ".h", ".c", ".cpp", ".ino", ".ini", ".txt", ".sh", ".service", ".cfg", ""}
#: docs/<path> not preceded by a path character (so "/elsewhere/docs/x" is not one); ends on a word character
DOCS_REFERENCE = re.compile(r"(?<![\w./-])docs/[\w./-]*\w")
MARKDOWN_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def repository_files() -> list[Path]:
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, text=True, check=True).stdout.split("\n")
    return [ROOT / name for name in listed if name and (ROOT / name).is_file()]


def docs_references(text: str) -> list[str]:
    return DOCS_REFERENCE.findall(text)


def test_the_reference_pattern_finds_what_it_should():
    text = "see docs/physics.md. Also (`docs/img/view.png`), docs/img/ and /work/other/docs/x.md, not mydocs/y"
    assert docs_references(text) == ["docs/physics.md", "docs/img/view.png", "docs/img"]


def test_every_docs_reference_resolves():
    missing = []
    for path in repository_files():
        if path.suffix not in TEXT_SUFFIXES or path.name == Path(__file__).name:
            continue
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue
        for reference in docs_references(text):
            if not (ROOT / reference).exists():
                missing.append(f"{path.relative_to(ROOT)}: {reference}")
        if path.parent == ROOT / "docs" and path.suffix == ".md":
            for target in MARKDOWN_LINK.findall(text):
                if "://" in target or target.startswith("mailto:"):
                    continue
                if not (path.parent / target).exists():
                    missing.append(f"{path.relative_to(ROOT)}: link {target}")
    assert not missing, "references to files that do not exist:\n" + "\n".join(missing)


def test_the_documents_the_code_points_to_exist():
    for name in ("architecture.md", "physics.md"):
        assert (ROOT / "docs" / name).stat().st_size > 1000
