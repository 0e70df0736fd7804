"""The files users and tools expect beside the code say the same as the code: the license pyproject.toml names,
the version `phantom --version` prints (in the changelog and the citation), the paper the citation names."""

import re
import tomllib
from pathlib import Path

import pytest

import phantom
from phantom.cli.main import main

REPO = Path(__file__).resolve().parent.parent


def test_phantom_version_prints_the_package_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.split() == ["phantom", phantom.__version__]
    assert re.fullmatch(r"\d+\.\d+\.\d+", phantom.__version__)


def test_the_license_file_is_the_one_pyproject_names():
    assert tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["license"] == "MIT"
    text = (REPO / "LICENSE").read_text()
    assert text.startswith("MIT License") and "Permission is hereby granted, free of charge" in text


def test_the_changelog_has_a_section_for_this_version():
    headings = re.findall(r"^## \[([^\]]+)\]", (REPO / "CHANGELOG.md").read_text(), re.MULTILINE)
    assert headings[0] == phantom.__version__


def test_the_citation_names_the_paper_its_authors_and_this_version():
    text = (REPO / "CITATION.cff").read_text()
    fields = dict(re.findall(r"^(\w[\w-]*): *(.*)$", text, re.MULTILINE))
    assert fields["cff-version"] == "1.2.0" and fields["version"] == phantom.__version__
    assert fields["license"] == "MIT"
    paper = text.split("preferred-citation:")[1]
    assert 'title: "Active Prostate Phantom with Multiple Chambers"' in paper
    assert re.findall(r"family-names: (\w+)", paper) == ["Tian", "Adagolodjo", "Dequidt"]
