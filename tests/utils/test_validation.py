"""The shared argument checks: exact messages, TypeError for a wrong type, ValueError for a wrong value."""

from __future__ import annotations

import re

import numpy as np
import pytest

from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_range, check_type


def _raises(error: type[Exception], message: str):
    return pytest.raises(error, match=f"^{re.escape(message)}$")


def test_check_type():
    assert check_type("name", "chair", str) == "chair"
    with _raises(TypeError, "`name` must be a str, got int 3"):
        check_type("name", 3, str)
    with _raises(TypeError, "`name` must be a str or bytes, got int 3"):
        check_type("name", 3, (str, bytes))
    with _raises(TypeError, "`selector` must be a ViewSelector, got list []"):
        check_type("selector", [], dict, "ViewSelector")
    with _raises(TypeError, "`x` must be an int, got str 'a'"):
        check_type("x", "a", int)


def test_check_int():
    assert check_int("k", 3) == 3 and type(check_int("k", np.int64(3))) is int
    assert check_int("k", 8, minimum=1, maximum=8) == 8
    with _raises(TypeError, "`k` must be an int, got float 1.0"):
        check_int("k", 1.0)
    with _raises(TypeError, "`k` must be an int, got bool True"):
        check_int("k", True)
    with _raises(ValueError, "`k` must be an int >= 1, got 0"):
        check_int("k", 0, minimum=1)
    with _raises(ValueError, "`k` must be an int <= 8, got 9"):
        check_int("k", 9, maximum=8)
    with _raises(ValueError, "`k` must be an int in [1, 8], got 9"):
        check_int("k", 9, minimum=1, maximum=8)


def test_check_float():
    assert check_float("x", 1) == 1.0 and type(check_float("x", np.float32(0.5))) is float
    assert check_float("x", 0.0, minimum=0.0) == 0.0
    with _raises(TypeError, "`x` must be a number, got str 'a'"):
        check_float("x", "a")
    with _raises(TypeError, "`x` must be a number, got bool False"):
        check_float("x", False)
    with _raises(ValueError, "`x` must be a finite number, got nan"):
        check_float("x", float("nan"))
    with _raises(ValueError, "`x` must be a finite number, got inf"):
        check_float("x", float("inf"), minimum=0.0)
    with _raises(ValueError, "`x` must be a number >= 0, got -2.0"):
        check_float("x", -2, minimum=0)
    with _raises(ValueError, "`x` must be a number > 0, got 0.0"):
        check_float("x", 0.0, minimum=0, min_open=True)
    with _raises(ValueError, "`x` must be a number < 1, got 1.0"):
        check_float("x", 1.0, maximum=1, max_open=True)
    with _raises(ValueError, "`x` must be a number in [0, 1), got 1.0"):
        check_float("x", 1.0, minimum=0, maximum=1, max_open=True)
    with _raises(ValueError, "`x` must be a number in (0, 1], got 0.0"):
        check_float("x", 0.0, minimum=0, maximum=1, min_open=True)


def test_check_choice():
    assert check_choice("mode", "area", ("angle", "area")) == "area"
    assert check_choice("mask", None, (None, "gt")) is None
    with _raises(ValueError, "`mode` must be one of 'angle', 'area', got 'disk'"):
        check_choice("mode", "disk", ("angle", "area"))
    with _raises(ValueError, "`mask` must be one of None, 'gt', got 'pred'"):
        check_choice("mask", "pred", (None, "gt"))
    # an unhashable value against a set or dict is simply not among the choices
    with _raises(ValueError, "`name` must be one of 'a', got ['a']"):
        check_choice("name", ["a"], {"a": 1})


def test_check_range():
    assert check_range("yaw_range", (-10, 20), -180, 180) == (-10.0, 20.0)
    assert check_range("pitch_range", np.array([0, 90]), -90, 90) == (0.0, 90.0)
    with _raises(ValueError, "`yaw_range` must satisfy -180 <= low <= high <= 180 (degrees), got (30, 10)"):
        check_range("yaw_range", (30, 10), -180, 180, "degrees")
    with _raises(ValueError, "`r` must satisfy 0 <= low <= high <= 1, got (-1, 0.5)"):
        check_range("r", (-1, 0.5), 0, 1)
    with _raises(TypeError, "`r` must be a pair (low, high) (degrees), got 5"):
        check_range("r", 5, 0, 1, "degrees")
    with _raises(TypeError, "`r` must be a pair (low, high), got (1, 2, 3)"):
        check_range("r", (1, 2, 3), 0, 1)
    with _raises(TypeError, "`r` must be a pair of numbers, got ('a', 1)"):
        check_range("r", ("a", 1), 0, 1)
