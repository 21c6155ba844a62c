"""``ns-verify-owner``: does a suspect model, or a folder of suspect images, carry an owner's message?

``cli`` parses the subcommands; ``check`` verifies (``verify``), ``calibrate`` measures a key's null, ``keys`` holds
``export-key`` and ``commit``, ``stats`` turns decoded views into verdicts and ``report`` writes them. The decoders
themselves live in :mod:`gsticker_plugin.decoders`. See docs/verify.md.
"""
