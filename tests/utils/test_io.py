"""Atomic writes: the destination is replaced whole or not at all, and no temporary file is left behind."""

from __future__ import annotations

import json

import pytest

from lightning_vtr.utils.io import atomic_open, atomic_write


def test_atomic_write_round_trips_text_and_bytes(tmp_path):
    text = tmp_path / "a" / "b" / "note.txt"  # parents are created
    atomic_write(text, "grüße\n")
    assert text.read_text(encoding="utf-8") == "grüße\n"
    blob = tmp_path / "blob.bin"
    atomic_write(blob, bytes(range(256)), fsync=True)
    assert blob.read_bytes() == bytes(range(256))
    atomic_write(blob, b"shorter")  # replaces, never appends
    assert blob.read_bytes() == b"shorter"
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["blob.bin", "note.txt"]


@pytest.mark.parametrize(("mode", "payload"), [("w", "new"), ("wb", b"new")])
def test_atomic_open_replaces_the_file_on_success(tmp_path, mode, payload):
    path = tmp_path / "out.json"
    path.write_text("old")
    with atomic_open(path, mode, fsync=True) as f:
        f.write(payload)
        assert path.read_text() == "old"  # readers see the old file until the block ends
    assert path.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


def test_atomic_open_keeps_the_old_file_and_no_temporary_when_the_body_raises(tmp_path):
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"run": 1}))
    with pytest.raises(RuntimeError, match="boom"), atomic_open(path, "w") as f:  # noqa: PT012 (a write, then the error)
        f.write('{"run": 2, "trunc')
        raise RuntimeError("boom")
    assert json.loads(path.read_text()) == {"run": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]


def test_atomic_open_without_an_existing_file_leaves_nothing_on_error(tmp_path):
    with pytest.raises(KeyboardInterrupt), atomic_open(tmp_path / "new.bin") as f:  # noqa: PT012 (a write, then the error)
        f.write(b"partial")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_atomic_open_rejects_other_modes(tmp_path):
    with pytest.raises(ValueError, match=r"^`mode` must be 'wb' or 'w', got 'a'$"), atomic_open(tmp_path / "x", "a"):
        pass
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_gives_the_permissions_of_a_plain_open(tmp_path):
    import os

    old = os.umask(0o022)
    try:
        atomic_write(tmp_path / "shared.png", b"x")
        (tmp_path / "plain.png").write_bytes(b"x")
    finally:
        os.umask(old)
    assert (tmp_path / "shared.png").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "shared.png").stat().st_mode & 0o777 == (tmp_path / "plain.png").stat().st_mode & 0o777
