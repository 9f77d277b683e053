"""The command blocks of README.md and docs/getting-started.md run, in order, as a reader pastes them into one
terminal: one bash session per page (so a variable a block sets, such as ``CKPT``, holds in the next), in a
scratch folder laid out like a clone (its ``examples/`` and ``configs/``), with this interpreter's ``python`` and
``lightning-vtr`` first on ``PATH``. ```` ```bash ```` blocks run as bash lines; ```` ```python ```` blocks run
with ``python`` in the same folder. A block that fails fails the test, naming the block, with the output's end.

What the pages may mark, with an HTML comment on the line before a block's opening fence (the site and GitHub show
neither):

* ``<!-- not run: REASON -->``: the block does not run. Among shell blocks exactly two per page carry it, checked
  by :func:`test_only_the_set_up_and_the_test_suite_are_skipped`: the set-up (clone, virtual environment,
  ``pip install``: this test runs in an environment set up so, without network) and ``python -m pytest`` (the
  suite that runs this test). A Python block carries it for the reason tests/test_docs_code.py states (an outline).
* ``<!-- test: FLAGS -->``: a block whose command trains for minutes on 2 cores runs with ``FLAGS`` added to each
  of its commands (smaller epoch or batch budgets); the command is otherwise the one printed.

The embedded dataset (75 s to build) is not built here: ``LIGHTNING_VTR_DATA`` points at a scratch folder that
holds a copy of the suite's small procedural dataset (tests/conftest.py) under the embedded dataset's name, so
``--data embedded``, the examples' default and the configs' ``root: null`` all read it.

After each page ran, the files and lines its commands promise (a table, ``last.ckpt`` where the page says fit
writes it, ``predictions/index.html``, ``maps/bins.csv``) are checked. The two pages take about two minutes each
on 2 cores: the tests are marked ``slow``.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "docs" / "getting-started.md"]
#: what the scratch folder links from the repository, as a clone has them
CLONE_ENTRIES = ("examples", "configs")
_FENCE = re.compile(r"^```+\s*(?P<lang>[\w+-]*)\s*$")
_SHELL = {"bash", "sh", "shell"}
_MARKER = re.compile(r"^\s*<!--\s*(?P<kind>not run|test):\s*(?P<value>.*?)\s*-->\s*$")
_COMMAND = re.compile(r"^(lightning-vtr|python)\s")
#: the commands a skipped shell block may hold: the set-up's and the test suite's
_SET_UP = re.compile(r"^(git clone |cd |python3? -m venv |\. \S+/activate|pip install )")
_TESTS = re.compile(r"^python -m pytest(\s|$)")


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    not_run: str | None  # the reason of a `<!-- not run: ... -->` marker
    flags: str | None  # the FLAGS of a `<!-- test: FLAGS -->` marker

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT).as_posix()}:{self.line}"


def blocks(path: Path) -> list[Block]:
    """The shell and Python blocks of a Markdown page, in order, with their markers."""
    lines = path.read_text(encoding="utf-8").splitlines()
    found: list[Block] = []
    i = 0
    while i < len(lines):
        fence = _FENCE.match(lines[i])
        if not fence:
            i += 1
            continue
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        lang = fence.group("lang").lower()
        if lang in _SHELL or lang == "python":
            before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
            marker = _MARKER.match(before)
            kind, value = (marker.group("kind"), marker.group("value")) if marker else (None, None)
            code = "\n".join(lines[i + 1 : end]) + "\n"
            found.append(Block(path, i + 1, "python" if lang == "python" else "bash", code, *_marked(kind, value)))
        i = end + 1
    return found


def _marked(kind: str | None, value: str | None) -> tuple[str | None, str | None]:
    return (value, None) if kind == "not run" else (None, value) if kind == "test" else (None, None)


def shell_commands(code: str) -> list[str]:
    """The logical lines of a shell block: ``\\`` continuations joined, blank and comment-only lines dropped."""
    commands: list[str] = []
    pending = ""
    for raw in code.splitlines():
        line = pending + raw.strip()
        if line.endswith("\\"):
            pending = line[:-1].rstrip() + " "
            continue
        pending = ""
        if line and not line.startswith("#"):
            commands.append(line)
    return commands


def _strip_comment(command: str) -> str:
    """``command`` without a trailing ``  # comment`` (the ``#`` outside quotes, after a space)."""
    quote = None
    for i, char in enumerate(command):
        if quote:
            quote = None if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char == "#" and i and command[i - 1].isspace():
            return command[:i].rstrip()
    return command


def with_flags(code: str, flags: str) -> tuple[str, int]:
    """The block's commands, each ``lightning-vtr ...`` / ``python ...`` one with ``flags`` added; and how many."""
    out, count = [], 0
    for command in shell_commands(code):
        if _COMMAND.match(command):
            command, count = f"{_strip_comment(command)} {flags}", count + 1
        out.append(command)
    return "\n".join(out) + "\n", count


def script(page: Path, folder: Path) -> str:
    """The bash script that runs ``page``'s blocks in order (Python blocks written under ``folder``)."""
    parts = ["set -eo pipefail"]
    for index, block in enumerate(blocks(page)):
        if block.not_run is not None:
            continue
        parts.append(f"echo '@@ block {block.name}'")
        if block.lang == "python":
            file = folder / f"block_{index:02d}.py"
            file.write_text(block.code, encoding="utf-8")
            parts.append(f"python {file}")
        elif block.flags is not None:
            code, count = with_flags(block.code, block.flags)
            assert count, f"{block.name}: `<!-- test: {block.flags} -->` marks a block with no command to add them to"
            parts.append(code)
        else:
            parts.append(block.code)
    return "\n".join(parts) + "\n"


#: page -> (files the commands write, relative to the scratch folder; lines they print, as regular expressions)
PROMISES = {
    "README.md": (
        ["runs/pix2vox_vtr/none/results.json"],
        [r"\| Pix2Vox\+\+ \(no VTR\) \|( [0-9.]+ \|){6}", r"\| Pix2Vox\+\+ \+ VTR \(default rule\) \|( [0-9.]+ \|){6}"],
    ),
    "docs/getting-started.md": (
        [
            "runs/pix2vox_vtr/none/results.json",
            "runs/cli/pix2vox_tiny_vtr/lightning_logs/version_0/checkpoints/last.ckpt",  # where the page says
            "predictions/index.html",
            "predictions/predictions.json",
            "maps/bins.csv",
            "maps/index.html",
        ],
        [
            r"\| Pix2Vox\+\+ \+ VTR \(default rule\) \|( [0-9.]+ \|){6}",
            r"\s*all\s+21\s+3\s+6\s+30",  # dataset-info's table of the small dataset
            r".*test/spherical/iou@0\.4.*",
            r"Wrote 18 objects to predictions; open predictions/index.html",  # 6 test objects x 3 view sets
        ],
    ),
}


def test_the_pages_show_the_commands_a_new_user_needs():
    found = {
        page.relative_to(ROOT).as_posix(): [c for b in blocks(page) for c in shell_commands(b.code)] for page in PAGES
    }
    assert set(found) == set(PROMISES)
    getting_started = found["docs/getting-started.md"]
    for expected in (
        r"git clone \S+ && cd \S+",
        r"python3 -m venv \.venv && \. \.venv/bin/activate",
        r"pip install torch==\S+.*",
        r'pip install -e "\.\[dev,zero123\]"',
        r"python examples/pix2vox_vtr\.py",
        r"lightning-vtr fit --config configs/\S+\.yaml.*",
        r'lightning-vtr (validate|test) --config configs/\S+\.yaml --ckpt_path "\$CKPT"',
        r'lightning-vtr predict --ckpt "\$CKPT" --data embedded .*',
        r'lightning-vtr robustness --ckpt "\$CKPT" --data embedded .*',
        r"python -m pytest -q",
    ):
        assert any(re.fullmatch(expected, command) for command in getting_started), f"no command {expected!r}"


@pytest.mark.parametrize("page", PAGES, ids=[page.name for page in PAGES])
def test_only_the_set_up_and_the_test_suite_are_skipped(page):
    skipped = [block for block in blocks(page) if block.lang == "bash" and block.not_run is not None]
    kinds = []
    for block in skipped:
        commands = shell_commands(block.code)
        assert block.not_run, f"{block.name}: write `<!-- not run: REASON -->`"
        if all(_SET_UP.match(command) for command in commands):
            kinds.append("set-up")
        elif [bool(_TESTS.match(command)) for command in commands] == [True]:
            kinds.append("tests")
        else:
            raise AssertionError(f"{block.name} is marked not run but holds other commands: {commands}")
    assert sorted(kinds) == ["set-up", "tests"], [block.name for block in skipped]


def test_flags_are_added_to_each_command_before_its_comment():
    code = (
        'R=x\nlightning-vtr fit --config "a #b.yaml"  # a comment\n# a comment line\npython examples/e.py \\\n  --k 1\n'
    )
    assert with_flags(code, "--n 1") == (
        'R=x\nlightning-vtr fit --config "a #b.yaml" --n 1\npython examples/e.py --k 1 --n 1\n',
        2,
    )


@pytest.fixture
def embedded_data(tiny_dataset, tmp_path, monkeypatch) -> Path:
    """``LIGHTNING_VTR_DATA`` set to a folder holding a copy of the small dataset under the embedded dataset's
    name (the copy, because the commands write into the dataset they train on)."""
    from lightning_vtr.data.builder import embedded_dataset_dir

    monkeypatch.setenv("LIGHTNING_VTR_DATA", str(tmp_path / "data"))
    shutil.copytree(tiny_dataset, embedded_dataset_dir())
    return tmp_path / "data"


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES, ids=[page.name for page in PAGES])
def test_the_pages_commands_run_in_order(page, embedded_data, tmp_path):
    scratch, blocks_dir = tmp_path / "clone", tmp_path / "blocks"
    scratch.mkdir()
    blocks_dir.mkdir()
    for entry in CLONE_ENTRIES:
        (scratch / entry).symlink_to(ROOT / entry)
    env = {**os.environ, "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])}
    bash = blocks_dir / "page.sh"
    bash.write_text(script(page, blocks_dir), encoding="utf-8")
    log = tmp_path / "output.log"
    with log.open("w", encoding="utf-8") as out:
        done = subprocess.run(
            ["bash", str(bash)], cwd=scratch, env=env, stdout=out, stderr=subprocess.STDOUT, timeout=1200, check=False
        )
    printed = log.read_text(encoding="utf-8", errors="replace")
    if done.returncode:
        failed = re.findall(r"^@@ block (\S+)$", printed, flags=re.M)
        raise AssertionError(
            f"{failed[-1] if failed else page.name} failed (exit status {done.returncode}); its output ends:\n"
            + printed[-3000:]
        )
    files, lines = PROMISES[page.relative_to(ROOT).as_posix()]
    missing = [file for file in files if not (scratch / file).is_file()]
    assert not missing, f"{page.name}'s commands did not write {missing}"
    printed_lines = printed.splitlines()
    for pattern in lines:
        assert any(re.fullmatch(pattern, line.rstrip()) for line in printed_lines), f"no printed line {pattern!r}"
