"""No command writes through a symlink: re-run on an earlier output folder (one copied from someone else) whose
files are links to files elsewhere, ``predict``, ``robustness`` and the report's writers replace each link with a
regular file and leave the file it pointed to as it was (content and modification time).

Every file is written by :mod:`lightning_vtr.utils.io`: a temporary file made with ``O_EXCL`` in the folder,
then ``os.replace``, which replaces a link instead of following it; the write probe of ``--out`` is an
unguessable ``O_EXCL`` file.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from helpers import one_thread, save_tiny_checkpoint

from lightning_vtr.cli import main

_one_thread = pytest.fixture(autouse=True)(one_thread)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny Pix2Vox++ checkpoint (64 px inputs)."""
    return save_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt")


@pytest.fixture(scope="module")
def data(tiny_dataset):
    """The suite's tiny dataset (64 px, three categories)."""
    return tiny_dataset


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and not p.is_symlink())


def _link_every_file(out: Path, outside: Path) -> dict[Path, tuple[Path, bytes, int]]:
    """Replace every file under ``out`` with a symlink to a file of its own under ``outside``; returns
    link -> (target, its content, its mtime in ns)."""
    links = {}
    for i, path in enumerate(_files(out)):
        target = outside / f"{i:03d}_{path.name}"
        target.write_bytes(f"someone else's file {i}\n".encode())
        os.utime(target, ns=(1_000_000_000, 1_000_000_000 + i))
        path.unlink()
        path.symlink_to(target)
        links[path] = (target, target.read_bytes(), target.stat().st_mtime_ns)
    return links


def _assert_untouched_and_replaced(links: dict[Path, tuple[Path, bytes, int]], outside: Path, before: int) -> None:
    for link, (target, content, mtime) in links.items():
        assert target.read_bytes() == content, f"{target} (linked from {link.name}) was written"
        assert target.stat().st_mtime_ns == mtime, f"{target} (linked from {link.name}) was touched"
    assert len(list(outside.iterdir())) == before  # nothing new appeared outside either
    rewritten = [link for link in links if link.exists() and not link.is_symlink()]
    assert rewritten == [link for link in links if link.exists()], "a link was left in place"


def test_predict_and_robustness_rerun_replace_links_and_never_write_through_them(checkpoint, data, tmp_path, capsys):
    outside = tmp_path / "outside"
    outside.mkdir()
    # predict: 2 objects of the test split, one view set
    out = tmp_path / "predict"
    predict = ["predict", "--ckpt", str(checkpoint), "--data", str(data), "--view-sets", "aligned", "--limit", "2"]
    predict += ["--out", str(out), "--no-progress"]
    assert main(predict) == 0, capsys.readouterr().err
    written = _files(out)
    assert {"predictions.json", "index.html", "prediction.binvox"} <= {p.name for p in written}
    links = _link_every_file(out, outside)
    before = len(list(outside.iterdir()))
    assert main(predict) == 0, capsys.readouterr().err
    _assert_untouched_and_replaced(links, outside, before)
    assert {p.relative_to(out) for p in links} <= {p.relative_to(out) for p in _files(out)}  # all written again

    # robustness: one checkpoint, 1 object, 8 bins
    out = tmp_path / "robustness"
    robustness = ["robustness", "--ckpt", f"tiny={checkpoint}", "--data", str(data), "--out", str(out)]
    robustness += ["--k", "90", "--objects", "1", "--no-progress", "--device", "cpu"]
    assert main(robustness) == 0, capsys.readouterr().err
    written = _files(out)
    assert {"bins.csv", "index.html", "tiny.png", "objects.csv", "robustness.json"} <= {p.name for p in written}
    links = _link_every_file(out, outside)
    before = len(list(outside.iterdir()))
    assert main(robustness) == 0, capsys.readouterr().err
    _assert_untouched_and_replaced(links, outside, before)
    assert sorted(links) == _files(out)  # every file written again, as a regular file


def test_the_report_writers_replace_links(tmp_path):
    """``results.csv``, ``differences.csv`` and ``report.png`` of an earlier report folder, each a link."""
    from lightning_vtr.experiments.report_files import write_chart, write_differences_csv, write_results_csv
    from lightning_vtr.experiments.report_plan import ReportRun
    from lightning_vtr.protocol import VIEW_SETS

    values = {"iou@0.3": 0.4, "iou@0.4": 0.5, "iou@0.5": 0.3, "fscore": 0.2}
    results = {view_set: dict(values) for view_set in VIEW_SETS}
    payloads = {name: {0: {"results": results, "train_seconds": 1.0}} for name in ("none", "random")}
    runs = [ReportRun(name, name) for name in payloads]
    rows = {"None-VTR": "none", "Random": "random"}
    out, outside = tmp_path / "out", tmp_path / "outside"
    out.mkdir()
    outside.mkdir()
    for name in ("results.csv", "differences.csv", "report.png"):
        (out / name).write_text("")
    links = _link_every_file(out, outside)
    write_results_csv(out / "results.csv", runs, payloads, [0])
    write_differences_csv(out / "differences.csv", rows, payloads, [0])
    write_chart(out / "report.png", rows, payloads, [0], {})
    _assert_untouched_and_replaced(links, outside, 3)
    assert (out / "results.csv").read_text().splitlines()[0].startswith("run,strategy,seed,view_set")
    assert (out / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_write_probe_is_unguessable_and_never_opens_a_planted_file(tmp_path):
    from lightning_vtr.cli.arguments import check_output_folder

    out = tmp_path / "out"
    out.mkdir()
    (out / "predictions.json").write_text("[]")  # an earlier output
    target = tmp_path / "victim.txt"
    target.write_text("keep me")
    for name in (f".write-probe-{os.getpid()}", ".write-probe"):  # the names an older version used
        (out / name).symlink_to(target)
    assert check_output_folder(out) == out
    assert target.read_text() == "keep me"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [".write-probe", f".write-probe-{os.getpid()}", "predictions.json"]
    )


def test_an_appended_log_refuses_a_symlink(tmp_path):
    from lightning_vtr.utils.io import open_append

    target = tmp_path / "victim.txt"
    target.write_text("keep me")
    (tmp_path / "run.log").symlink_to(target)
    with pytest.raises(OSError, match="a symlink: refusing to write through it"):
        open_append(tmp_path / "run.log")
    assert target.read_text() == "keep me"
    with open_append(tmp_path / "fresh.log") as log:
        log.write("one\n")
    with open_append(tmp_path / "fresh.log") as log:
        log.write("two\n")
    assert (tmp_path / "fresh.log").read_text() == "one\ntwo\n"


def test_join_under_lets_a_writer_replace_a_linked_file_but_not_enter_a_linked_folder(tmp_path):
    from lightning_vtr.utils.paths import UnsafePathError, join_under

    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    (out / "a.png").symlink_to(elsewhere / "a.png")
    (out / "maps").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(UnsafePathError):
        join_under(out, "a.png")  # a reader would follow the link out
    assert join_under(out, "a.png", replace_link=True) == out / "a.png"  # a writer replaces it
    for parts in (("maps", "x.png"), ("..", "x.png"), ("sub", "..", "..")):
        with pytest.raises(UnsafePathError):
            join_under(out, *parts, replace_link=True)
