"""The argparse types the sub-commands share."""

from __future__ import annotations

import argparse

import pytest

from lightning_vtr.cli.arguments import comma_separated, positive_int, ratios, shard


def test_shard():
    assert shard("3/16") == (3, 16) and shard("0/1") == (0, 1)
    for text, message in (("3/2", "0 <= i < n"), ("-1/4", "0 <= i < n"), ("1/0", "0 <= i < n"), ("a/b", "i/n")):
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            shard(text)


def test_comma_separated_with_and_without_choices():
    assert comma_separated()(" chair, table,,") == ["chair", "table"]
    with pytest.raises(argparse.ArgumentTypeError, match="comma-separated"):
        comma_separated()(" , ")
    strategies = comma_separated(("none", "random"))
    assert strategies("random,none") == ["random", "none"]
    with pytest.raises(argparse.ArgumentTypeError, match=r"invalid choice\(s\) 'ours' \(choose from none, random\)"):
        strategies("none,ours")


def test_ratios_and_positive_int():
    assert ratios("0.7,0.1,0.2") == (0.7, 0.1, 0.2)
    for text in ("0.7,0.3", "a,b,c"):
        with pytest.raises(argparse.ArgumentTypeError, match="three comma-separated ratios"):
            ratios(text)
    assert positive_int("4") == 4
    for text in ("0", "-2", "1.5", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match="positive integer"):
            positive_int(text)


def test_dataset_folder_names_the_embedded_dataset_by_a_word(tiny_dataset, monkeypatch):
    from lightning_vtr.cli.arguments import dataset_folder
    from lightning_vtr.data import builder

    built = []
    monkeypatch.setattr(
        builder, "ensure_embedded_dataset", lambda progress=True: built.append(progress) or tiny_dataset
    )
    assert dataset_folder("embedded", progress=False) == tiny_dataset
    assert built == [False]
    assert dataset_folder(str(tiny_dataset)) == tiny_dataset  # a folder is itself
    assert built == [False]


def test_a_folder_of_datasets_is_refused_naming_the_datasets_inside(tiny_dataset, tmp_path):
    from lightning_vtr.cli.arguments import dataset_folder
    from lightning_vtr.data.format import DatasetNotFoundError

    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "embedded-0123456789").symlink_to(tiny_dataset, target_is_directory=True)
    (cache / "notes").mkdir()
    with pytest.raises(DatasetNotFoundError) as error:
        dataset_folder(cache)
    message = str(error.value)
    assert "is a folder of datasets, not a dataset: it holds embedded-0123456789;" in message
    assert "notes" not in message and "`embedded`" in message
    with pytest.raises(
        FileNotFoundError, match=r"`--data` must be a ShapeNet-VTR directory or `embedded`, got .* \(no such folder\)"
    ):
        dataset_folder(tmp_path / "missing")
