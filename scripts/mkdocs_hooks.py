"""MkDocs hooks (``hooks:`` in mkdocs.yml): the pages made at build time and the nav's globs.

- ``cli.md``, the command line: every subcommand's usage and help, from
  ``agents.cli.build_parser()``, so that the page cannot go stale.
- ``api/``, the API reference: one page per sub-package (``api/estimation/ukf.md``) with a
  mkdocstrings block (``::: estimation.ukf.filter``) for each of its modules, found on disk;
  a package's top-level modules are on its index page (``api/estimation/index.md``).
- The nav of mkdocs.yml may hold globs, matched against the site's pages (generated ones
  included), so that pages added to ``docs/envs/``, ``docs/estimators/``,
  ``docs/results/`` appear without editing the nav:

  - a string with ``*``, ``?`` or ``[...]`` stands for the pages it matches, ``index.md``
    first, then by path; ``**`` crosses folders, each sub-folder a section of its own;
  - ``"A | B"``: the first alternative that matches a page; the pages of the others are
    left out of the site (``estimators/*.md | estimators.md``: the folder, once it exists,
    replaces the single page);
  - a titled entry (``Results: results/*.md``) is a section of its matches, the page itself
    where there is one match, and is dropped where there is none (an optional page:
    ``extending*.md``);
  - a page ``X.md`` beside a glob over ``X/`` in the same section is that section's index
    page (``navigation.indexes``), as an ``X/index.md`` would be; where ``X/index.md``
    exists, that is the index, and ``X.md`` is served at ``X/X/`` (both would be ``X/``).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Iterator

    from mkdocs.config.defaults import MkDocsConfig
    from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("tensegrity_gym", "estimation", "hardware", "agents")
"""The packages the API reference covers, in its order."""
CLI_PAGE = "cli.md"
API_DIR = "api"
_GLOB = re.compile(r"[*?\[]")


# --- set-up -----------------------------------------------------------------------------


def on_config(config: MkDocsConfig) -> MkDocsConfig:
    """Import the packages from this checkout; read snippets from the repository root
    wherever mkdocs runs from."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    snippets = config.mdx_configs.get("pymdownx.snippets")
    if snippets is not None:
        base = snippets.get("base_path", ["."])
        base = [base] if isinstance(base, str) else base
        snippets["base_path"] = [str((ROOT / b).resolve()) for b in base]
    # griffe reads an extension's path from the working directory: make it the root's.
    python = config.plugins["mkdocstrings"].config["handlers"]["python"]
    options = python.setdefault("options", {})
    options["extensions"] = [
        str(ROOT / e) if isinstance(e, str) and e.partition(":")[0].endswith(".py") else e
        for e in options.get("extensions", [])
    ]
    return config


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the generated pages, then resolve the nav's globs against all the pages."""
    from mkdocs.structure.files import File

    generated = {CLI_PAGE: cli_markdown(), **api_pages()}
    for uri, text in generated.items():
        present = files.get_file_from_path(uri)
        if present is not None and present.generated_by is None:
            raise RuntimeError(
                f"docs/{uri} is generated at build time by scripts/mkdocs_hooks.py: delete it"
            )
        files.append(File.generated(config, uri, content=text))
    if config.nav is not None:
        pages = sorted(f.src_uri for f in files.documentation_pages())
        left_out: set[str] = set()
        config.nav = _expand_list(config.nav, pages, left_out, files)
        for uri in left_out:
            file = files.get_file_from_path(uri)
            if file is not None:
                files.remove(file)
    return files


# --- the command line -------------------------------------------------------------------


@contextlib.contextmanager
def _columns(width: int) -> Iterator[None]:
    """argparse wraps its help to $COLUMNS: a fixed width, whatever the terminal."""
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(width)
    try:
        yield
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, Any]]:
    """(one-line help, parser) of each subcommand, in the parser's order."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:  # aliases share a parser
                    seen.add(id(sub))
                    out.append((helps.get(name, ""), sub))
    return out


def cli_markdown() -> str:
    """The command line page: each (sub)command's ``--help``."""
    from agents.cli import build_parser

    with _columns(100):
        parser = build_parser()
        lines = [
            "# Command line",
            "",
            "Generated at build time from `agents.cli.build_parser()`: the output of "
            f"`{parser.prog} --help` and of each `{parser.prog} COMMAND --help`.",
            "",
            "```text",
            parser.format_help().rstrip(),
            "```",
            "",
        ]

        def walk(p: argparse.ArgumentParser, level: int) -> None:
            for help_, sub in _subcommands(p):
                lines.extend([f"{'#' * level} {sub.prog}", ""])
                if help_:
                    lines.extend([_md_text(help_[0].upper() + help_[1:]) + ".", ""])
                lines.extend(["```text", sub.format_help().rstrip(), "```", ""])
                walk(sub, min(level + 1, 6))

        walk(parser, 2)
    return "\n".join(lines)


def _md_text(text: str) -> str:
    """Help text as Markdown prose: nothing in it read as markup."""
    return re.sub(r"([\\`*_\[\]<>#|])", r"\\\1", text.rstrip(". "))


# --- the API reference ------------------------------------------------------------------


def _plain_modules(package_dir: Path, dotted: str) -> list[str]:
    """The public modules directly in a package (not its sub-packages)."""
    return [
        f"{dotted}.{p.stem}" for p in sorted(package_dir.glob("*.py")) if not p.name.startswith("_")
    ]


def _subpackages(package_dir: Path) -> list[Path]:
    return [
        p
        for p in sorted(package_dir.iterdir())
        if (p / "__init__.py").is_file() and not p.name.startswith("_")
    ]


def _all_modules(package_dir: Path, dotted: str) -> list[str]:
    """The package, its modules, then its sub-packages' the same way."""
    out = [dotted, *_plain_modules(package_dir, dotted)]
    for sub in _subpackages(package_dir):
        out.extend(_all_modules(sub, f"{dotted}.{sub.name}"))
    return out


def _page(title: str, modules: list[str]) -> str:
    blocks = [f"::: {module}\n" for module in modules]
    return "\n".join([f"# `{title}`\n", *blocks])


def api_pages() -> dict[str, str]:
    """``api/index.md`` and, for each package, ``api/PKG/index.md`` (the package and its
    own modules) and ``api/PKG/SUB.md`` (a sub-package and all the modules below it)."""
    pages: dict[str, str] = {}
    index = [
        "# API reference",
        "",
        "Generated at build time from the docstrings: a page for each sub-package.",
        "",
        "| package | sub-packages |",
        "|---|---|",
    ]
    for package in PACKAGES:
        pdir = ROOT / package
        pages[f"{API_DIR}/{package}/index.md"] = _page(
            package, [package, *_plain_modules(pdir, package)]
        )
        subs = _subpackages(pdir)
        for sub in subs:
            dotted = f"{package}.{sub.name}"
            pages[f"{API_DIR}/{package}/{sub.name}.md"] = _page(dotted, _all_modules(sub, dotted))
        links = ", ".join(f"[`{s.name}`]({package}/{s.name}.md)" for s in subs)
        index.append(f"| [`{package}`]({package}/index.md) | {links} |")
    pages[f"{API_DIR}/index.md"] = "\n".join([*index, ""])
    return pages


# --- the nav's globs --------------------------------------------------------------------


def _regex(pattern: str) -> re.Pattern[str]:
    """A glob as a regular expression over '/'-separated paths (``**`` crosses folders)."""
    out, i = "", 0
    while i < len(pattern):
        c = pattern[i]
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        elif c == "*":
            out, i = out + "[^/]*", i + 1
        elif c == "?":
            out, i = out + "[^/]", i + 1
        elif c == "[":
            j = pattern.index("]", i + 1)
            out, i = out + pattern[i : j + 1], j + 1
        else:
            out, i = out + re.escape(c), i + 1
    return re.compile(out + r"\Z")


def _is_pattern(value: str) -> bool:
    return bool(_GLOB.search(value)) or "|" in value


def _order(uri: str) -> tuple[str, int, str]:
    folder, _, name = uri.rpartition("/")
    return (folder, name != "index.md", name)


def _match(pattern: str, pages: list[str]) -> list[str]:
    if not _GLOB.search(pattern):
        return [pattern] if pattern in pages else []
    regex = _regex(pattern)
    return sorted((p for p in pages if regex.match(p)), key=_order)


def _resolve(value: str, pages: list[str], left_out: set[str]) -> tuple[str, list[str]]:
    """(the alternative taken, its pages); the other alternatives' pages go to left_out."""
    chosen: tuple[str, list[str]] | None = None
    for alternative in (a.strip() for a in value.split("|")):
        if not alternative:
            continue
        matches = _match(alternative, pages)
        if chosen is None and matches:
            chosen = (alternative, matches)
        else:
            left_out.update(matches)
    if chosen is None:
        return "", []
    left_out.difference_update(chosen[1])
    return chosen


def _nest(pattern: str, matches: list[str]) -> list[Any]:
    """Matches of a ``**`` glob as nav entries: the pages of each sub-folder (below the
    pattern's fixed part) in a section named after the folder."""
    fixed = pattern[: _GLOB.search(pattern).start()]  # type: ignore[union-attr]
    base = fixed.rpartition("/")[0]
    base = f"{base}/" if base else ""
    tree: dict[str, Any] = {}
    for uri in matches:
        node = tree
        *folders, _ = uri[len(base) :].split("/")
        for folder in folders:
            node = node.setdefault(folder + "/", {})
        node[uri] = None

    def entries(node: dict[str, Any]) -> list[Any]:
        pages = sorted((k for k, v in node.items() if v is None), key=_order)
        folders = sorted(k for k, v in node.items() if v is not None)
        return [*pages, *({f[:-1]: entries(node[f])} for f in folders)]

    return entries(tree)


def _pages_of(value: str, pages: list[str], left_out: set[str]) -> list[Any]:
    alternative, matches = _resolve(value, pages, left_out)
    return _nest(alternative, matches) if "**" in alternative else matches


def _expand_list(items: list[Any], pages: list[str], left_out: set[str], files: Files) -> list[Any]:
    out: list[Any] = []
    for item in items:
        if isinstance(item, str):
            out.extend(_pages_of(item, pages, left_out) if _is_pattern(item) else [item])
        elif isinstance(item, dict) and len(item) == 1:
            ((title, value),) = item.items()
            if isinstance(value, str) and _is_pattern(value):
                entries = _pages_of(value, pages, left_out)
                if len(entries) == 1 and isinstance(entries[0], str):
                    out.append({title: entries[0]})
                elif entries:
                    out.append({title: entries})
            elif isinstance(value, list):
                out.append({title: _expand_list(value, pages, left_out, files)})
                _mark_index(value, files)
            else:
                out.append(item)
        else:
            out.append(item)
    return out


def _mark_index(section: list[Any], files: Files) -> None:
    """A page ``X.md`` beside a glob over ``X/`` is its section's index page; where the
    folder has an ``index.md`` of its own, that one is, and ``X.md`` a page of the section
    at ``X/X/`` (not at ``X/``, the folder index's URL)."""
    globs = [
        v
        for e in section
        for v in ([e] if isinstance(e, str) else (e.values() if isinstance(e, dict) else []))
        if isinstance(v, str) and _is_pattern(v)
    ]
    for entry in section:
        uri = entry if isinstance(entry, str) else None
        if isinstance(entry, dict) and len(entry) == 1:
            (value,) = entry.values()
            uri = value if isinstance(value, str) else None
        if uri is None or _is_pattern(uri) or not uri.endswith(".md"):
            continue
        folder = uri[: -len(".md")] + "/"
        file = files.get_file_from_path(uri)
        if file is None or not any(g.startswith(folder) for g in globs):
            continue
        if files.get_file_from_path(folder + "index.md") is None:
            _make_index(file)
        elif file.use_directory_urls:
            stem = folder.rstrip("/").rpartition("/")[2]
            file.dest_uri = f"{folder}{stem}/index.html"
            file.url = f"{folder}{stem}/"


def _make_index(file: File) -> None:
    """Let ``file`` count as an index page (mkdocs: a file named index) at its own URL."""
    dest, url = file.dest_uri, file.url
    file.dest_uri, file.url = dest, url  # fixed before the name changes
    file.name = "index"
