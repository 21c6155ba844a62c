"""What the purification attack fine-tunes (gsticker_plugin.recolor.purify)."""

from torch import nn

from gsticker_plugin.recolor.purify import purify_parameters


def test_purification_fits_every_float_parameter_but_the_scene_box_and_the_decoding_heads():
    model = nn.Module()
    model.field = nn.Linear(2, 2)
    model.sticker = nn.Linear(2, 1)
    model.extractor = nn.Linear(2, 48)
    model.classifier = nn.Linear(2, 1)
    model.register_parameter("aabb", nn.Parameter(nn.init.zeros_(nn.Linear(2, 3).weight)))
    assert sorted(purify_parameters(model)) == ["field.bias", "field.weight", "sticker.bias", "sticker.weight"]
