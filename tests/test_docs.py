"""The documentation site's build-time machinery (scripts/mkdocs_hooks.py,
scripts/griffe_extensions.py). The site itself is built, strict, by scripts/test.sh."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent


def _load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


hooks = _load("mkdocs_hooks")


def _files(uris: list[str]):  # type: ignore[no-untyped-def]
    from mkdocs.structure.files import File, Files

    return Files([File(uri, "/docs", "/site", use_directory_urls=True) for uri in uris])


def test_nav_globs_expand_choose_and_drop() -> None:
    uris = [
        "index.md",
        "envs.md",
        "envs/B-v0.md",
        "envs/A-v0.md",
        "envs/hardware/A-v0.md",
        "estimators.md",
        "estimators/index.md",
        "estimators/ukf.md",
        "results/demo.md",
        "api/index.md",
        "api/pkg/index.md",
        "api/pkg/sub.md",
    ]
    files = _files(uris)
    nav = [
        {"Home": "index.md"},
        {"Environments": ["envs.md", "envs/*.md", {"Hardware": "envs/hardware/*.md"}]},
        {"Estimators": "estimators/*.md | estimators.md"},
        {"Extending": "extending*.md"},
        {"Results": "results/*.md"},
        {"API": "api/**/*.md"},
    ]
    left_out: set[str] = set()
    pages = sorted(f.src_uri for f in files.documentation_pages())
    assert hooks._expand_list(nav, pages, left_out, files) == [
        {"Home": "index.md"},
        {
            "Environments": [
                "envs.md",
                "envs/A-v0.md",
                "envs/B-v0.md",
                {"Hardware": "envs/hardware/A-v0.md"},
            ]
        },
        {"Estimators": ["estimators/index.md", "estimators/ukf.md"]},
        {"Results": "results/demo.md"},
        {"API": ["api/index.md", {"pkg": ["api/pkg/index.md", "api/pkg/sub.md"]}]},
    ]
    assert left_out == {"estimators.md"}  # the folder replaces the page
    envs = files.get_file_from_path("envs.md")
    assert envs.name == "index" and envs.url == "envs/"  # the section's index page


def test_a_folder_index_takes_the_section() -> None:
    files = _files(["envs.md", "envs/index.md", "envs/A-v0.md"])
    nav = [{"Environments": ["envs.md", "envs/*.md"]}]
    pages = ["envs.md", "envs/A-v0.md", "envs/index.md"]
    assert hooks._expand_list(nav, pages, set(), files) == [
        {"Environments": ["envs.md", "envs/index.md", "envs/A-v0.md"]}
    ]
    envs = files.get_file_from_path("envs.md")
    assert envs.name == "envs" and envs.url == "envs/envs/"  # not the folder index's URL


def test_nav_falls_back_to_the_single_page() -> None:
    files = _files(["estimators.md"])
    left_out: set[str] = set()
    nav = [{"Estimators": "estimators/*.md | estimators.md"}]
    assert hooks._expand_list(nav, ["estimators.md"], left_out, files) == [
        {"Estimators": "estimators.md"}
    ]
    assert not left_out


def test_cli_page_has_every_subcommand() -> None:
    from agents.cli import build_parser

    page = hooks.cli_markdown()
    commands = [sub.prog for _, sub in hooks._subcommands(build_parser())]
    assert len(commands) >= 10
    for prog in commands:
        assert f"## {prog}\n" in page


def test_api_reference_covers_every_module() -> None:
    blocks = {
        line.removeprefix("::: ")
        for text in hooks.api_pages().values()
        for line in text.splitlines()
        if line.startswith("::: ")
    }
    for package in hooks.PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if any(p.startswith("_") for p in parts[:-1]):
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            elif parts[-1].startswith("_"):
                continue
            assert ".".join(parts) in blocks


def test_grouped_parameters_are_split() -> None:
    split = _load("griffe_extensions").split_grouped
    text = (
        "Do.\n\nArgs:\n    a: x.\n    b, c: the two\n        of them.\n\nRaises:\n    E, F: no.\n"
    )
    assert split(text) == (
        "Do.\n\nArgs:\n    a: x.\n    b: the two\n        of them.\n"
        "    c: the two\n        of them.\n\nRaises:\n    E, F: no."
    )


def test_sphinx_roles_become_code_spans() -> None:
    plain = _load("griffe_extensions").plain_roles
    text = "see :class:`~a.b.C`, :meth:`D.f` and ``x``"
    assert plain(text) == "see ``C``, ``D.f`` and ``x``"


@pytest.mark.parametrize("package", ["estimation.ukf", "estimation.inekf", "estimation.icp"])
def test_a_papers_reference_is_written_alike_in_code_and_docs(package: str) -> None:
    """The full reference an estimator's docstring gives is the references page's."""
    import importlib
    import re

    doc = importlib.import_module(package).__doc__ or ""
    found = re.search(r"Reference: (.*?)\n\n|Reference: (.*)$", doc, re.S)
    assert found, f"{package}: no 'Reference:' in its docstring"
    reference = " ".join((found.group(1) or found.group(2)).split()).rstrip(".")
    page = " ".join((ROOT / "docs" / "references.md").read_text().split())
    plain = re.sub(r"\*", "", page)  # the page sets the venue in italics
    assert reference in plain, f"{package}: {reference!r} is not on docs/references.md"
