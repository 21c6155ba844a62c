from gsticker_plugin.evaluation.cli import entrypoint

entrypoint()
