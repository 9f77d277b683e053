"""MkDocs hook: fill ``cli.md``'s marker with every sub-command's options, add MathJax to the site, and fix
the changelog's links.

``mkdocs.yml`` names this file under ``hooks:``. The marker ``<!-- cli-options -->`` in ``docs/cli.md`` is
replaced by one section per sub-command of :func:`lightning_vtr.cli.build_parser`, holding its ``--help``
text, so the page always lists the options the installed command accepts: the package's own commands from their
parsers, ``fit`` / ``validate`` / ``test`` (LightningCLI) from ``lightning-vtr COMMAND --help`` run in a fresh
process, as a user runs it (the classes it lists are those a fresh process knows).

The site's formulas are typeset by MathJax served with the site, not from a CDN, so that a reader offline sees
them: :func:`on_files` adds MathJax's single-file SVG build (``tex-svg.js``, which needs no font files)
from the installed ``django-static-mathjax`` distribution (the ``docs`` and ``dev`` extras; it ships MathJax's
files and needs no Django) as ``assets/mathjax/tex-svg.js`` of the built site, which ``mkdocs.yml`` loads.

``docs/changelog.md`` includes the repository's ``CHANGELOG.md``, whose links into the docs start with ``docs/``
so that they work where the file lives; on the site the page already sits in ``docs``, so the prefix goes.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

MARKER = "<!-- cli-options -->"
#: where the built site keeps MathJax (``mkdocs.yml``'s ``extra_javascript`` names it)
MATHJAX_SITE_PATH = "assets/mathjax/tex-svg.js"


def mathjax_script() -> Path:
    """MathJax's single-file SVG build (``es5/tex-svg.js``) in the installed ``django-static-mathjax``.

    Raises:
        FileNotFoundError: the distribution is not installed (``pip install -e ".[docs]"`` installs it).
    """
    import importlib.util

    spec = importlib.util.find_spec("mathjax")
    script = Path(spec.origin).parent / "static" / "mathjax" / "es5" / "tex-svg.js" if spec and spec.origin else None
    if script is None or not script.is_file():
        raise FileNotFoundError(
            "the docs need MathJax from the `django-static-mathjax` package (mathjax/static/mathjax/es5/tex-svg.js), "
            'found none: pip install -e ".[docs]"'
        )
    return script


def lightning_help(command: str) -> str:
    """What ``lightning-vtr COMMAND --help`` prints, run in a fresh process (this interpreter's command)."""
    env = {**os.environ, "COLUMNS": "100"}
    beside = Path(sys.executable).parent / "lightning-vtr"  # this interpreter's, as in a virtual environment
    program = str(beside) if beside.is_file() else shutil.which("lightning-vtr") or "lightning-vtr"
    done = subprocess.run(
        [program, command, "--help"],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    if done.returncode:
        raise RuntimeError(f"`lightning-vtr {command} --help` exited with {done.returncode}: {done.stderr[-2000:]}")
    return done.stdout


def cli_reference() -> str:
    """Markdown: a section per sub-command with its help line and its ``--help`` output."""
    os.environ["COLUMNS"] = "100"  # argparse wraps the help text at the terminal width
    from lightning_vtr.cli import build_parser
    from lightning_vtr.cli.dispatch import LIGHTNING_COMMANDS

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    helps = {choice.dest: choice.help for choice in sub._choices_actions}
    parts = []
    for name, command in sub.choices.items():
        text = lightning_help(name) if name in LIGHTNING_COMMANDS else command.format_help()
        parts.append(f"## {name}\n\n{helps.get(name) or ''}\n\n```text\n{text.rstrip()}\n```\n")
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


def on_files(files, config):
    """Add MathJax to the site's files (see the module docstring): built and served with the pages."""
    from mkdocs.structure.files import File

    files.append(File.generated(config, MATHJAX_SITE_PATH, abs_src_path=str(mathjax_script())))
    return files
