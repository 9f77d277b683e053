"""The README stays short, every page under docs/ is in mkdocs.yml's nav (and every nav entry exists), and the
changelog's links into the docs resolve.

No site is built here: the checks read README.md, CHANGELOG.md, mkdocs.yml and the docs folder only.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README_MAX_LINES = 250


def _nav_pages(entries) -> list[str]:
    """Every page path in a MkDocs nav (lists of strings and one-key mappings, nested)."""
    pages: list[str] = []
    for entry in entries:
        if isinstance(entry, str):
            pages.append(entry)
        elif isinstance(entry, dict):
            for value in entry.values():
                if isinstance(value, str):
                    pages.append(value)
                else:
                    pages.extend(_nav_pages(value))
    return [page for page in pages if "://" not in page]  # external links are not pages


def _config() -> dict:
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; at most {README_MAX_LINES}"


def test_docs_dir_is_docs():
    assert _config().get("docs_dir", "docs") == "docs"


def test_every_page_is_in_the_nav():
    nav = set(_nav_pages(_config()["nav"]))
    pages = {path.relative_to(DOCS).as_posix() for path in DOCS.rglob("*.md")}
    assert not pages - nav, f"pages missing from mkdocs.yml's nav: {sorted(pages - nav)}"


def test_every_nav_entry_exists():
    nav = _nav_pages(_config()["nav"])
    missing = [page for page in nav if not (DOCS / page).is_file()]
    assert not missing, f"mkdocs.yml's nav names pages that do not exist under docs/: {missing}"
    assert len(nav) == len(set(nav)), "a page appears twice in mkdocs.yml's nav"


def _slug(heading: str) -> str:
    """The anchor MkDocs (Python-Markdown's toc) gives a heading: lower case, punctuation dropped, spaces to -."""
    text = re.sub(r"[^\w\s-]", "", heading.strip().lower())
    return re.sub(r"[\s]+", "-", text)


def test_the_changelogs_links_into_the_docs_resolve_in_the_repository_and_on_the_site():
    import importlib.util
    from types import SimpleNamespace

    text = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\((docs/[^)#]+)(?:#([^)]+))?\)", text)
    assert links, "the changelog links its evidence into the docs"
    for path, anchor in links:
        target = ROOT / path
        assert target.is_file(), f"CHANGELOG.md links {path}, which does not exist"
        if anchor:
            headings = re.findall(r"^#+ (.+)$", target.read_text(encoding="utf-8"), flags=re.M)
            assert anchor in {_slug(h) for h in headings}, f"{path} has no heading for #{anchor}"
    # the site's changelog page includes the file with the links made relative to docs/
    spec = importlib.util.spec_from_file_location("gen_cli", DOCS / "gen_cli.py")
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page = SimpleNamespace(file=SimpleNamespace(src_uri="changelog.md"))
    source = (DOCS / "changelog.md").read_text(encoding="utf-8")
    rendered = hook.on_page_markdown(source, page, {"docs_dir": str(DOCS)}, None)
    assert "](docs/" not in rendered and "--8<--" not in rendered
    assert f"]({links[0][0].removeprefix('docs/')}" in rendered


def test_the_nav_puts_user_docs_first_and_names_each_entry_once():
    top = [next(iter(entry)) for entry in _config()["nav"]]
    assert top[:6] == ["Home", "Getting started", "Guides", "Command line", "API reference", "Evidence"], top

    def check(entries, parent):
        titles = [title for entry in entries for title in entry]
        assert all(isinstance(entry, dict) for entry in entries), f"an untitled entry under {parent!r}: {entries}"
        repeated = sorted({title for title in titles if titles.count(title) > 1} | ({parent} & set(titles)))
        assert not repeated, f"mkdocs.yml's nav repeats {repeated} under {parent!r}"
        for entry in entries:
            for title, value in entry.items():
                if isinstance(value, list):
                    check(value, title)

    check(_config()["nav"], "lightning_vtr")


def test_every_page_has_one_title():
    for path in sorted(DOCS.rglob("*.md")):
        if path.name == "changelog.md":
            continue  # the page is CHANGELOG.md, included by the docs hook
        prose = re.sub(r"^\s*```.*?^\s*```", "", path.read_text(encoding="utf-8"), flags=re.M | re.S)
        titles = re.findall(r"^# .+$", prose, flags=re.M)
        assert len(titles) == 1, f"{path.relative_to(ROOT)} has {len(titles)} H1 titles: {titles}"


def test_the_site_names_no_temporary_folder():
    for path in sorted(DOCS.rglob("*.md")):
        text = path.read_text(encoding="utf-8")
        assert "/tmp/" not in text, f"{path.relative_to(ROOT)} names a temporary folder (/tmp/)"


def _hook():
    import importlib.util

    spec = importlib.util.spec_from_file_location("gen_cli", DOCS / "gen_cli.py")
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    return hook


def _listed_options(help_text: str) -> set[str]:
    """The options a ``--help`` text lists: the option strings at the start of its entries (``  -c X, --config X``)."""
    options = set()
    for line in help_text.splitlines():
        if re.match(r"^  -", line):
            entry = re.split(r"\s{2,}", line.strip(), maxsplit=1)[0]  # the option strings, before the description
            options |= set(re.findall(r"(?:^|, )(--?[\w.+-]+)", entry))
    return options


def _live_options() -> dict[str, set[str]]:
    """Each sub-command's options, read from the live parsers' actions (hidden ones left out)."""
    import argparse

    from lightning_vtr.cli import build_parser
    from lightning_vtr.cli.dispatch import LIGHTNING_COMMANDS
    from lightning_vtr.cli.lightning import VTRLightningCLI

    def shown(parser) -> set[str]:
        return {s for a in parser._actions for s in a.option_strings if a.help != argparse.SUPPRESS}

    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    options = {name: shown(parser) for name, parser in sub.choices.items() if name not in LIGHTNING_COMMANDS}

    class _Parsed(Exception):
        pass

    class _ParserOnly(VTRLightningCLI):
        def parse_arguments(self, parser, args) -> None:
            options.update(
                {name: shown(parser._subcommands_action._name_parser_map[name]) for name in LIGHTNING_COMMANDS}
            )
            raise _Parsed

    with pytest.raises(_Parsed):  # stopped once the parser is built, before anything is instantiated
        _ParserOnly(args=["fit"], parser_kwargs={"exit_on_error": False})
    return options


def test_the_command_line_page_lists_exactly_each_commands_options():
    # the page the site builds: docs/cli.md with the hook's sections, one per sub-command
    from types import SimpleNamespace

    page = SimpleNamespace(file=SimpleNamespace(src_uri="cli.md"))
    source = (DOCS / "cli.md").read_text(encoding="utf-8")
    rendered = _hook().on_page_markdown(source, page, {"docs_dir": str(DOCS)}, None)
    sections = dict(re.findall(r"^## (\S+)\n\n.*?\n\n```text\n(.*?)\n```", rendered, flags=re.M | re.S))
    live = _live_options()
    assert set(sections) == set(live), f"the page has sections {sorted(sections)}, the command {sorted(live)}"
    for name, text in sections.items():
        listed = _listed_options(text)
        assert listed == live[name], (
            f"`lightning-vtr {name}`: the page lists {sorted(listed - live[name])} that the parser lacks and lacks "
            f"{sorted(live[name] - listed)}"
        )
    assert {"--trainer.max_epochs", "--ckpt_path", "--model", "--data.image_size"} <= live["fit"]
    assert {"--ckpt", "--data", "--out"} <= live["robustness"] and "--scores" not in live["robustness"]


def test_the_option_reader_finds_each_entrys_options():
    text = (
        "usage: x [-h]\n\noptions:\n  -h, --help            show this help\n  -c CONFIG, --config CONFIG\n"
        "                        a config; see --other\n  --trainer.callbacks CALLBACKS, --trainer.callbacks+ CALLBACKS\n"
        "  --ckpt [NAME=]CKPT    a checkpoint (--not-this)\n"
    )
    assert _listed_options(text) == {
        "-h",
        "--help",
        "-c",
        "--config",
        "--trainer.callbacks",
        "--trainer.callbacks+",
        "--ckpt",
    }
