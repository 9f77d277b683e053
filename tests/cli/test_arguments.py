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
