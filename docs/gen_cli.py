"""MkDocs hook: fill ``cli.md``'s marker with every sub-command's options, and fix the changelog's links.

``mkdocs.yml`` names this file under ``hooks:``. The marker ``<!-- cli-options -->`` in ``docs/cli.md`` is
replaced by one section per sub-command of :func:`lightning_vtr.cli.build_parser`, holding its ``--help``
text, so the page always lists the options the installed command accepts.

``docs/changelog.md`` includes the repository's ``CHANGELOG.md``, whose links into the docs start with ``docs/``
so that they work where the file lives; on the site the page already sits in ``docs``, so the prefix goes.
"""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

MARKER = "<!-- cli-options -->"


def cli_reference() -> str:
    """Markdown: a section per sub-command with its help line and its ``--help`` output."""
    os.environ["COLUMNS"] = "100"  # argparse wraps the help text at the terminal width
    from lightning_vtr.cli import build_parser

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    helps = {choice.dest: choice.help for choice in sub._choices_actions}
    parts = []
    for name, command in sub.choices.items():
        parts.append(f"## {name}\n\n{helps.get(name) or ''}\n\n```text\n{command.format_help().rstrip()}\n```\n")
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER in markdown:
        markdown = markdown.replace(MARKER, cli_reference())
    if page.file.src_uri == "changelog.md":
        # include the changelog here rather than through the snippets extension, which runs after this hook
        changelog = Path(config["docs_dir"]).parent / "CHANGELOG.md"
        text = re.sub(r"\]\(docs/", "](", changelog.read_text(encoding="utf-8"))
        markdown = markdown.replace('--8<-- "CHANGELOG.md"', text)
    return markdown
