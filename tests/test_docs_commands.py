"""Every ``lightning-vtr ...`` and ``python examples/...`` command in README.md and docs/**/*.md parses with the
real parsers, so a renamed or removed option fails here. Nothing runs: the commands are only parsed.

Where the commands are found:

* shell blocks (```` ```bash ````, ```` ```console ````, ```` ```text ```` ...): every line that starts with a
  command (after ``$ `` in a transcript, where only ``$`` lines are commands), with ``\\`` continuations joined,
  ``#`` comments dropped and ``&&`` / ``|`` / ``;`` ending a command;
* inline code spans that start with a command (`` `lightning-vtr dataset-info OUT --verify` ``); a span is
  often a fragment (an option to add), so its sub-command and options must exist, not its required ones.

How each is parsed:

* the package's own sub-commands (``build-dataset``, ``report``, ``predict``, ...): ``parse_args`` of
  :func:`lightning_vtr.cli.build_parser`. A command with ``...`` standing for elided arguments is checked
  option by option: every ``--option`` it names must be one of that sub-command's options. A sub-command named
  alone (`` `lightning-vtr predict` ``) must exist; ``lightning-vtr COMMAND`` (a placeholder) is not checked;
* LightningCLI's ``fit`` / ``validate`` / ``test`` / ``predict --config ...``: the package's
  ``VTRLightningCLI`` parses the words (configs read, ``class_path`` entries resolved and their arguments
  checked) and stops before any class is instantiated; the placeholder ``CONFIG`` stands for a ready-made config;
* ``python examples/NAME.py ...``: the example's own ``parse_args(argv)``; an example without one takes no
  arguments.

Placeholders in capitals (``OUT``, ``ROOT``, ``DATASET``) are plain values to argparse and stay as written. A
Python block the docs tell the reader to save (``<!-- file: mymodel.py -->`` on the line before it) is saved so,
in a folder on ``sys.path``, so that ``--model mymodel.MyVoxelNet`` resolves as it does in the reader's folder.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
PROGRAMS = ("lightning-vtr", "python examples/")
#: placeholder word -> what is parsed instead
PLACEHOLDERS = {"CONFIG": "configs/pix2vox_tiny_vtr.yaml", "CONFIG.yaml": "configs/pix2vox_tiny_vtr.yaml"}
_FENCE = re.compile(r"^\s*```+\s*(?P<lang>[\w+-]*)")
_SHELL_LANGS = {"", "bash", "sh", "shell", "console", "text", "zsh"}
_SPAN = re.compile(r"(?<!`)`(?P<code>(?:lightning-vtr|python examples/)[^`]*)`(?!`)")
_OPERATORS = {"&&", "||", "|", ";", "&", ">", ">>", "<", "2>", "2>&1"}
_FILE_MARKER = re.compile(r"^\s*<!--\s*file:\s*(?P<name>\w+\.py)\s*-->\s*$")


@dataclass(frozen=True)
class Command:
    path: Path
    line: int
    words: tuple[str, ...]  # the command's words, from the program name on
    inline: bool = False  # an inline code span (often a fragment: its options are checked, not its completeness)

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT).as_posix()}:{self.line}: {shlex.join(self.words)[:90]}"


def _words(text: str) -> list[list[str]]:
    """The commands of one shell line: its words, split at operators, comments and ``VAR=value`` prefixes
    dropped; only the commands that start with one of :data:`PROGRAMS`."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars="|&;<>")
    lexer.whitespace_split = True
    lexer.commenters = "#"
    commands: list[list[str]] = [[]]
    for word in lexer:
        if word in _OPERATORS or set(word) <= set("|&;<>"):
            commands.append([])
        elif not commands[-1] and re.fullmatch(r"[A-Za-z_]\w*=.*", word):
            continue  # an environment assignment before the program
        else:
            commands[-1].append(word)
    found = []
    for words in commands:
        if words[:1] == ["lightning-vtr"] or (
            words[:1] == ["python"] and words[1:2] and words[1].startswith("examples/")
        ):
            found.append(words)
    return found


def doc_commands(path: Path) -> list[Command]:
    """Every command of :data:`PROGRAMS` in the Markdown file ``path`` (see the module docstring)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    commands: list[Command] = []
    i = 0
    while i < len(lines):
        fence = _FENCE.match(lines[i])
        if fence:
            end = next((j for j in range(i + 1, len(lines)) if lines[j].strip().startswith("```")), len(lines))
            if fence.group("lang").lower() in _SHELL_LANGS:
                block = lines[i + 1 : end]
                transcript = any(line.lstrip().startswith("$ ") for line in block)
                k = 0
                while k < len(block):
                    start, text = k, block[k].strip()
                    while text.endswith("\\") and k + 1 < len(block):
                        k += 1
                        text = text[:-1] + " " + block[k].strip()
                    k += 1
                    if transcript:
                        if not text.startswith("$ "):
                            continue  # printed output
                        text = text[2:]
                    if text.startswith(PROGRAMS) or re.match(r"[A-Za-z_]\w*=\S*\s+(lightning-vtr|python)", text):
                        commands += [Command(path, i + 2 + start, tuple(w)) for w in _words(text)]
            i = end + 1
            continue
        for span in _SPAN.finditer(lines[i]):
            commands += [Command(path, i + 1, tuple(w), inline=True) for w in _words(span.group("code"))]
        i += 1
    return commands


COMMANDS = [command for path in DOC_FILES for command in doc_commands(path)]


def doc_files(path: Path) -> dict[str, str]:
    """The Python blocks of ``path`` that the page has the reader save as a file: file name -> code."""
    lines = path.read_text(encoding="utf-8").splitlines()
    files = {}
    for i, line in enumerate(lines):
        marker = _FILE_MARKER.match(line)
        if marker:
            assert lines[i + 1].strip() == "```python", f"{path}:{i + 1}: a file marker must precede a python block"
            end = next(j for j in range(i + 2, len(lines)) if lines[j].strip() == "```")
            files[marker.group("name")] = "\n".join(lines[i + 2 : end]) + "\n"
    return files


@pytest.fixture(scope="module")
def saved_doc_files(tmp_path_factory):
    """The docs' files (:func:`doc_files`) saved in a folder on ``sys.path``, as in the reader's working folder."""
    import sys

    folder = tmp_path_factory.mktemp("reader")
    files = {name: code for path in DOC_FILES for name, code in doc_files(path).items()}
    for name, code in files.items():
        (folder / name).write_text(code, encoding="utf-8")
    sys.path.insert(0, str(folder))
    yield files
    sys.path.remove(str(folder))
    for name in files:
        sys.modules.pop(name.removesuffix(".py"), None)


def _package_parser() -> argparse.ArgumentParser:
    from lightning_vtr.cli import build_parser

    return build_parser()


def _subparser(name: str) -> argparse.ArgumentParser:
    parser = _package_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert name in sub.choices, f"`lightning-vtr {name}` is not a sub-command (they are: {sorted(sub.choices)})"
    return sub.choices[name]


class _Parsed(Exception):
    """Raised by :class:`_ParseOnly` once the words are parsed, before anything is instantiated."""


def _parse_lightning(words: list[str]) -> None:
    from lightning_vtr.cli.lightning import VTRLightningCLI

    class _ParseOnly(VTRLightningCLI):
        def parse_arguments(self, parser, args) -> None:
            super().parse_arguments(parser, args)
            raise _Parsed

    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            _ParseOnly(args=words, parser_kwargs={"exit_on_error": False})
    except _Parsed:
        return
    except SystemExit as exit_:  # --help and --print_config print and exit 0
        if exit_.code not in (0, None):
            raise AssertionError(out.getvalue()[-2000:]) from None
        return
    raise AssertionError("LightningCLI went past parsing")


def _parse_example(script: str, words: list[str]) -> None:
    path = ROOT / script
    assert path.is_file(), f"{script} does not exist"
    spec = importlib.util.spec_from_file_location(f"_docs_example_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "parse_args"):
        assert not words, f"{script} takes no arguments (it has no parse_args), got {words}"
        return
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            module.parse_args(words)
    except SystemExit as exit_:
        if exit_.code not in (0, None):
            raise AssertionError(f"{script} rejects {words}: {err.getvalue().strip()}") from None


def parse(words: tuple[str, ...], fragment: bool = False) -> None:
    """Parse one documented command with its real parser; raises ``AssertionError`` or the parser's error.

    With ``fragment`` (an inline span), a package sub-command's options are checked by name only, as with ``...``.
    """
    words_ = [PLACEHOLDERS.get(word, word) for word in words]
    if words_[0] == "python":
        _parse_example(words_[1], words_[2:])
        return
    args = words_[1:]
    from lightning_vtr.cli.dispatch import goes_to_lightning

    if not args or re.fullmatch(r"[A-Z][A-Z_]*:?", args[0]):
        return  # the bare program name, or `lightning-vtr COMMAND`, as in prose
    if goes_to_lightning(args):
        _parse_lightning(args)
        return
    command = _subparser(args[0])
    if len(args) == 1:
        return  # a sub-command named in prose (`lightning-vtr predict`): it exists
    if fragment or "..." in args:  # elided arguments: check the options it names
        known = {option for action in command._actions for option in action.option_strings}
        named = {word.split("=", 1)[0] for word in args[1:] if word.startswith("-")}
        unknown = sorted(named - known)
        assert not unknown, f"`lightning-vtr {args[0]}` has no option {unknown}"
        return
    _package_parser().parse_args(args)


def test_the_docs_have_commands_to_check():
    # the extraction finds commands of each kind (a changed format would otherwise make the test below vacuous)
    programs = {command.words[0] if command.words[0] != "python" else command.words[1] for command in COMMANDS}
    assert {"lightning-vtr", "examples/pix2vox_vtr.py"} <= programs
    kinds = {command.words[1] for command in COMMANDS if command.words[0] == "lightning-vtr" and len(command.words) > 1}
    assert {"fit", "report", "predict", "robustness", "build-dataset"} <= kinds, kinds


def test_extraction_joins_continuations_and_skips_output(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "Run `lightning-vtr dataset-info OUT --verify` first.\n\n"
        "```console\n$ lightning-vtr report --data /d \\\n    --seeds 0 1  # three\n"
        "lightning-vtr report: error: printed output, not a command\n```\n\n"
        '```bash\nR=runs/x\nlightning-vtr predict --ckpt "$R/a b.ckpt" --out p && python examples/quickstart.py\n```\n',
        encoding="utf-8",
    )
    found = [command.words for command in doc_commands(page)]
    assert [command.inline for command in doc_commands(page)] == [True, False, False, False]
    assert found == [
        ("lightning-vtr", "dataset-info", "OUT", "--verify"),
        ("lightning-vtr", "report", "--data", "/d", "--seeds", "0", "1"),
        ("lightning-vtr", "predict", "--ckpt", "$R/a b.ckpt", "--out", "p"),
        ("python", "examples/quickstart.py"),
    ]


def test_a_stale_option_fails():
    from lightning_vtr.errors import UsageError

    with pytest.raises(UsageError, match="--validation-triplets"):
        parse(("lightning-vtr", "report", "--validation-triplets", "12"))
    with pytest.raises(AssertionError, match="no option"):
        parse(("lightning-vtr", "robustness", "--ckpt", "a.ckpt", "...", "--no-such-option"))
    with pytest.raises(AssertionError, match="no option"):
        parse(("lightning-vtr", "predict", "--no-such-option"), fragment=True)
    parse(("lightning-vtr", "predict", "--model", "lrgt"), fragment=True)  # a fragment may omit required options
    with pytest.raises(UsageError, match="required"):
        parse(("lightning-vtr", "predict", "--model", "lrgt"))  # a whole command may not
    with pytest.raises(AssertionError, match="rejects"):
        parse(("python", "examples/pix2vox_vtr.py", "--no-such-option"))
    with pytest.raises(AssertionError, match="not a sub-command"):
        parse(("lightning-vtr", "compare", "--out", "x"))
    with pytest.raises(Exception, match="no_such_option"):
        parse(("lightning-vtr", "fit", "--config", "CONFIG", "--trainer.no_such_option", "1"))


def test_the_docs_files_are_found():
    assert "mymodel.py" in doc_files(ROOT / "docs" / "guide" / "models.md")


@pytest.mark.parametrize("command", COMMANDS, ids=[command.name for command in COMMANDS])
def test_documented_command_parses(command, saved_doc_files):
    parse(command.words, fragment=command.inline)
