"""Baselines the evaluation compares the sticker with (the colour-branch mark)."""
