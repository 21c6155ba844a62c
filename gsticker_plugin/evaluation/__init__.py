"""``ns-gsticker-eval``: the whole evaluation protocol (issue 6) from one YAML file.

``config`` (protocol dataclasses and YAML loading), ``runner`` (the stages: scene, bases, sticker, renders,
quality, distortions, curves, recolor, false positives, speed), ``report`` (results.md and charts), ``cli``.
"""
