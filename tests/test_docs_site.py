"""The built site: it loads nothing from another host (MathJax is served with it, so formulas typeset offline), and
its command line page lists the LightningCLI commands' options.

Builds the site once, as CI does (``mkdocs build --strict``), into a temporary folder: about a minute on 2 cores,
so the test is marked ``slow``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlparse

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: the site's own addresses (mkdocs.yml's site_url and repo_url), which pages may link to
SITE_HOSTS = {"lightning-vtr.readthedocs.io"}
#: what a page loads as it opens: scripts, stylesheets, fonts, images (links a reader follows are not loaded)
_LOADED = re.compile(
    r"<script[^>]*\ssrc=\"(?P<script>[^\"]+)\"|<link[^>]*\shref=\"(?P<link>[^\"]+)\"[^>]*>|<img[^>]*\ssrc=\"(?P<img>[^\"]+)\""
)


def loaded_hosts(html: str) -> set[str]:
    """The hosts other than the site's of what ``html`` loads (``<script src>``, ``<link href>`` other than the
    page's canonical address, ``<img src>``)."""
    hosts = set()
    for match in _LOADED.finditer(html):
        url = match.group("script") or match.group("img") or match.group("link")
        if match.group("link") and re.search(r"rel=\"(canonical|alternate)\"", match.group(0)):
            continue  # the page's own address, not loaded
        host = urlparse(url).netloc
        if host and host not in SITE_HOSTS:
            hosts.add(host)
    return hosts


def test_loaded_hosts_reads_scripts_links_and_images():
    html = (
        '<link rel="canonical" href="https://lightning-vtr.readthedocs.io/cli/">'
        '<link rel="stylesheet" href="https://fonts.googleapis.com/css?family=Roboto">'
        '<script src="../assets/mathjax/tex-svg.js"></script><script src="https://cdn.jsdelivr.net/npm/mathjax@3/x.js">'
        '</script><img alt="" src="https://example.org/a.png"><a href="https://github.com/x">a link</a>'
    )
    assert loaded_hosts(html) == {"fonts.googleapis.com", "cdn.jsdelivr.net", "example.org"}


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return out


@pytest.mark.slow
def test_the_site_loads_nothing_from_another_host(site):
    pages = sorted(site.rglob("*.html"))
    assert len(pages) > 20
    for page in pages:
        hosts = loaded_hosts(page.read_text(encoding="utf-8"))
        assert not hosts, f"{page.relative_to(site)} loads from {sorted(hosts)}"
    # MathJax itself is in the site, and the pages with formulas load it from there
    mathjax = site / "assets" / "mathjax" / "tex-svg.js"
    assert mathjax.is_file() and b"MathJax" in mathjax.read_bytes()[:20000]
    metrics = (site / "api" / "metrics" / "index.html").read_text(encoding="utf-8")
    assert 'class="arithmatex"' in metrics and 'src="../../assets/mathjax/tex-svg.js"' in metrics


@pytest.mark.slow
def test_the_command_line_page_shows_the_lightningcli_options(site):
    page = (site / "cli" / "index.html").read_text(encoding="utf-8")
    for command in ("fit", "validate", "test"):
        section = page.split(f'<h2 id="{command}"', 1)[1].split("<h2 ", 1)[0]
        for option in ("--trainer.max_epochs", "--ckpt_path", "--model", "--data.image_size", "--config"):
            assert option in section, f"the `{command}` section of cli.md lacks {option}"
    assert "--scores" not in page  # a research option, not the command's
