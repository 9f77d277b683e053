"""A user's selector as the callback meets it: settings derived from its constructor when it has no ``settings()``
(recorded, compared on resume), and its output checked right after ``select`` returns."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from helpers import TinyUserModel, make_callback, make_datamodule, make_trainer

from lightning_vtr.selection.base import ViewSelector, check_selection, constructor_settings, json_setting


class Marker:
    """An argument object without a repr of its own."""


SCALE = torch.tensor(2.0)


class Tilted(ViewSelector):
    """A user's selector with no ``settings()``: views at ``pitch`` and the given yaws."""

    def __init__(self, pitch=20.0, yaws=(0.0, 120.0, 240.0), *, jitter=None, scale=SCALE, helper=None):
        self.pitch, self._yaws, self.jitter, self.scale = pitch, yaws, jitter, scale
        self.helper = Marker() if helper is None else helper

    def select(self, predicted, target, categories, generator=None, context=None):
        views = torch.tensor([[yaw, self.pitch] for yaw in self._yaws])
        return views.expand(predicted.shape[0], 3, 2).clone()


class Returns(ViewSelector):
    """Returns whatever it was built with, for every object."""

    def __init__(self, views, batched=False):
        self.views, self.batched = views, batched

    def select(self, predicted, target, categories, generator=None, context=None):
        return self.views


def test_settings_derive_from_the_constructor_and_are_recorded_by_the_callback():
    selector = Tilted(pitch=30.0, jitter=[1, 2])
    expected = {
        "pitch": 30.0,
        "yaws": [0.0, 120.0, 240.0],  # read from `_yaws`, the tuple as a list
        "jitter": [1, 2],
        "scale": 2.0,  # a tensor as its value
        "helper": f"{Marker.__module__}.Marker",  # an object without a repr of its own: its class path
    }
    assert selector.settings() == constructor_settings(selector) == expected
    assert json.loads(json.dumps(expected)) == expected
    assert repr(
        selector
    ) == "Tilted(pitch=30.0, yaws=[0.0, 120.0, 240.0], jitter=[1, 2], scale=2.0, helper='{}')".format(
        expected["helper"]
    )
    callback = make_callback(selector=selector)
    # the callback's record, its checkpointed rule and its repr all hold them
    assert callback.settings()["selector_settings"] == expected
    assert callback.rule()["selector_settings"] == expected
    assert callback.state_dict()["rule"]["selector_settings"] == expected
    assert "Tilted(pitch=30.0, " in repr(callback)


def test_json_setting_keeps_plain_values_and_names_objects():
    assert json_setting({"a": (1, np.float32(0.5)), 2: {"b"}}) == {"a": [1, 0.5], "2": ["b"]}
    assert json_setting(torch.nn.functional.relu) == "torch.nn.functional.relu"
    assert json_setting(Tilted) == f"{Tilted.__module__}.Tilted"
    assert json_setting(slice(1, 2)) == "slice(1, 2, None)"  # an object with its own repr: the repr
    nested = json_setting(Tilted(pitch=5.0))  # an object with settings(): its class path and settings
    assert nested["class_path"] == f"{Tilted.__module__}.Tilted" and nested["init_args"]["pitch"] == 5.0


def test_a_resume_with_other_settings_of_a_user_selector_warns_naming_each():
    saved = make_callback(selector=Tilted(pitch=20.0)).state_dict()
    resumed = make_callback(selector=Tilted(pitch=35.0, yaws=(0.0, 90.0, 180.0)))
    with pytest.warns(UserWarning, match="belongs to another rule") as caught:
        resumed.load_state_dict(saved)
    (message,) = [str(w.message) for w in caught if "belongs to another rule" in str(w.message)]
    assert [line for line in message.splitlines() if line.startswith("  ")] == [
        "  Tilted.pitch: 20.0 in the checkpoint, 35.0 now",
        "  Tilted.yaws: [0.0, 120.0, 240.0] in the checkpoint, [0.0, 90.0, 180.0] now",
    ]
    same = make_callback(selector=Tilted(pitch=20.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        same.load_state_dict(saved)  # the same settings: restored without a word
    assert same.last_epoch == saved["last_epoch"]


@pytest.mark.parametrize(
    ("views", "message"),
    [
        (
            torch.zeros(3, 2),
            "Returns.select must return viewpoints of shape (objects, num_views, 2) = (1, 3, 2), got (3, 2)",
        ),
        (
            np.zeros((1, 3, 2)),
            "Returns.select must return a torch.Tensor of shape (objects, num_views, 2) = (1, 3, 2) (yaw, pitch in "
            "degrees), got numpy.ndarray",
        ),
        (
            torch.tensor([[[0.0, 0.0], [float("nan"), 10.0], [0.0, 0.0]]]),
            "Returns.select must return finite (yaw, pitch) angles, got [nan, 10.0] for object 0, view 1 (1 of 3 "
            "viewpoints)",
        ),
        (
            torch.tensor([[[0.0, 0.0], [0.0, 95.0], [10.0, -120.0]]]),
            "Returns.select must return pitches in [-90, 90] degrees, got [0.0, 95.0] for object 0, view 1 (2 of 3 "
            "viewpoints)",
        ),
        (
            torch.ones(1, 3, 2, dtype=torch.bool),
            "Returns.select must return real (yaw, pitch) angles in degrees, got dtype torch.bool",
        ),
    ],
)
def test_check_selection_names_the_selector_the_contract_and_what_it_returned(views, message):
    with pytest.raises(ValueError, match="^Returns.select must return ") as caught:
        check_selection(Returns(views), views, 1)
    assert str(caught.value) == message


def test_check_selection_passes_a_valid_selection_and_converts_integer_angles():
    views = torch.tensor([[[400, 90], [-30, -90], [0, 0]]])
    checked = check_selection(Returns(views), views, 1)
    assert checked.dtype == torch.get_default_dtype() and checked.tolist() == [
        [[400.0, 90.0], [-30.0, -90.0], [0.0, 0.0]]
    ]


@pytest.mark.parametrize("batched", [False, True], ids=["per_object", "batched"])
def test_a_fit_stops_at_a_wrong_selection_with_one_line_naming_the_selector(tiny_dataset, tmp_path, batched):
    callback = make_callback(selector=Returns(torch.zeros(5, 2), batched=batched))
    trainer = make_trainer(tmp_path, 1, [callback])
    with pytest.raises(
        ValueError, match="^Returns.select must return "
    ) as caught:  # the round before epoch 0: nothing rendered, nothing trained
        trainer.fit(TinyUserModel(), datamodule=make_datamodule(tiny_dataset, tmp_path))
    searched = 1 if not batched else round(0.2 * 21)  # per object, or every searched object in one call
    assert str(caught.value) == (
        f"Returns.select must return viewpoints of shape (objects, num_views, 2) = ({searched}, 3, 2), got (5, 2)"
    )
    assert trainer.global_step == 0 and not (tmp_path / "gen").exists()
