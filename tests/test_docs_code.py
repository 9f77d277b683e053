"""The Python code blocks of README.md, docs/index.md, docs/getting-started.md and docs/guide/*.md run as pasted.

Each block runs on its own (a fresh namespace, as if pasted into a new interpreter) in a temporary working
directory. Two kinds of change are made before running, and only these:

* :data:`SUBSTITUTIONS`, textual replacements that keep a block fast on 2 CPU cores (a 20-epoch fit becomes one
  batch per stage; the embedded dataset, 75 s to build, becomes a 2-category dataset built here in seconds).
  Each entry must still be used by some block, so the table cannot go stale.
* none other: a block that cannot run here (a ``...`` body, paths such as ``/data/...`` or ``/weights/...``,
  downloads, ``strategy="ddp", devices=8``) is marked in the Markdown with ``<!-- not run: REASON -->`` on the
  line before its opening fence, and is listed by :func:`test_not_run_markers_name_a_reason_and_a_block`.

A ``print(...)  # EXPECTED`` line documents its output: the block must print a line matching ``EXPECTED`` (the
part before `` = ``, where ``...`` stands for any text).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [
    ROOT / "README.md",
    ROOT / "docs" / "index.md",
    ROOT / "docs" / "getting-started.md",
    *sorted((ROOT / "docs" / "guide").glob("*.md")),
]
DATASET = "{dataset}"  # replaced by the directory of the dataset built by the `dataset` fixture
#: text in a block -> what runs instead; every entry must match at least one block.
SUBSTITUTIONS = {
    # a 20-epoch fit -> one training and one validation batch, writing no logs or checkpoints
    "max_epochs=20": (
        "max_epochs=1, limit_train_batches=1, limit_val_batches=1, logger=False, enable_checkpointing=False, "
        "enable_progress_bar=False, enable_model_summary=False"
    ),
    # the embedded dataset (built on first use, 75 s) -> the small dataset of the `dataset` fixture
    "VTRDataModule(image_size=64)": f"VTRDataModule({DATASET!r}, image_size=64, batch_size=4)",
}
_FENCE_OPEN = re.compile(r"^(\s*)```python\s*$")
_FENCE_CLOSE = re.compile(r"^\s*```\s*$")
_NOT_RUN = re.compile(r"^\s*<!--\s*not run:\s*(?P<reason>.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # 1-based line of the opening fence
    code: str
    not_run: str | None  # the reason of a `<!-- not run: ... -->` marker just before the block

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT).as_posix()}:{self.line}"


def python_blocks(path: Path) -> list[Block]:
    """The ```` ```python ```` blocks of a Markdown file, dedented, with their not-run markers."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        opening = _FENCE_OPEN.match(lines[i])
        if not opening:
            i += 1
            continue
        indent = len(opening.group(1))
        end = next(j for j in range(i + 1, len(lines)) if _FENCE_CLOSE.match(lines[j]))
        code = "\n".join(line[indent:] for line in lines[i + 1 : end]) + "\n"
        before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        marker = _NOT_RUN.match(before)
        blocks.append(Block(path, i + 1, code, marker.group("reason") if marker else None))
        i = end + 1
    return blocks


ALL_BLOCKS = [block for path in DOC_FILES for block in python_blocks(path)]
RUN_BLOCKS = [block for block in ALL_BLOCKS if block.not_run is None]


def substitute(code: str, dataset: Path) -> tuple[str, set[str]]:
    """``code`` with :data:`SUBSTITUTIONS` applied, and the keys that matched."""
    used = {key for key in SUBSTITUTIONS if key in code}
    for key in used:
        code = code.replace(key, SUBSTITUTIONS[key].replace(DATASET, str(dataset)))
    return code, used


def documented_output(code: str) -> list[re.Pattern[str]]:
    """One pattern per ``print(...)  # EXPECTED`` line: EXPECTED up to `` = ``, ``...`` matching any text."""
    patterns = []
    for line in code.splitlines():
        if line.lstrip().startswith("print(") and "  # " in line:
            expected = line.split("  # ", 1)[1].split(" = ", 1)[0].strip()
            patterns.append(re.compile(".*".join(map(re.escape, expected.split("..."))) + r"\s*"))
    return patterns


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A ShapeNet-VTR directory of 2 procedural categories x 6 objects at 64 px, 3 views per set."""
    from lightning_vtr.data.builder import build_dataset

    root = tmp_path_factory.mktemp("docs_vtr")
    build_dataset(
        root,
        source="procedural",
        categories=["chair", "table"],
        objects_per_category=6,
        image_size=64,
        resolution=32,
        views_per_set=3,
        seed=0,
        workers=1,
        progress=False,
    )
    return root


def test_the_pages_have_blocks_to_run():
    # the parser finds the blocks (a changed fence style would otherwise make every test below vacuous)
    names = {block.name.split(":")[0] for block in RUN_BLOCKS}
    assert {"docs/index.md", "docs/guide/callback.md", "docs/guide/data.md", "docs/guide/predict.md"} <= names
    assert len(RUN_BLOCKS) >= 7


def test_every_substitution_is_used():
    used = set().union(*(substitute(block.code, Path("x"))[1] for block in RUN_BLOCKS))
    assert used == set(SUBSTITUTIONS), f"unused substitutions: {sorted(set(SUBSTITUTIONS) - used)}"


def test_not_run_markers_name_a_reason_and_a_block():
    for path in DOC_FILES:
        lines = path.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines):
            if "not run" in line and "<!--" in line:
                marker = _NOT_RUN.match(line)
                assert marker and marker.group("reason"), f"{path}:{i + 1}: write `<!-- not run: REASON -->`"
                after = next((lines[j] for j in range(i + 1, len(lines)) if lines[j].strip()), "")
                # a shell block's marker is tests/test_docs_run.py's (README.md, getting-started.md)
                assert _FENCE_OPEN.match(after) or re.match(r"^\s*```bash\s*$", after), (
                    f"{path}:{i + 1}: a not-run marker must precede a python or bash block"
                )
    skipped = {block.name: block.not_run for block in ALL_BLOCKS if block.not_run is not None}
    assert len(skipped) <= len(ALL_BLOCKS) // 2, f"most blocks are marked not run: {skipped}"


def test_documented_output_patterns():
    (pattern,) = documented_output("x = 1\nprint(x, y)  # (3, 3, 224, 224) 0.88... = 240 / 255 * 2 - 1\n")
    assert pattern.fullmatch("(3, 3, 224, 224) 0.8823529481887817")
    assert not pattern.fullmatch("(3, 3, 224, 223) 0.8823529481887817")
    assert not pattern.fullmatch("(3, 3, 224, 224) 0.79")


@pytest.mark.parametrize("block", RUN_BLOCKS, ids=[block.name for block in RUN_BLOCKS])
def test_block_runs_as_pasted(block, dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # Trainers and exports write into the working directory
    code, _ = substitute(block.code, dataset)
    exec(compile(code, block.name, "exec"), {"__name__": "__main__"})
    printed = capsys.readouterr().out.splitlines()
    for pattern in documented_output(block.code):
        assert any(pattern.fullmatch(line) for line in printed), f"no printed line matches {pattern.pattern!r}"
