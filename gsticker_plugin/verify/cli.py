"""``ns-verify-owner``: does a suspect model, or a folder of suspect images, carry an owner's message?

Four subcommands (``verify`` is the default and may be left out)::

    ns-verify-owner [verify] (--load-config RUN/config.yml | --images DIR) (--key KEY.gskey | --keys DIR) [...]
    ns-verify-owner calibrate --key KEY.gskey [--load-config RUN/config.yml ...] [--images DIR ...] [...]
    ns-verify-owner export-key --load-config WATERMARKED_RUN/config.yml --key KEY.gskey [--output NEW.gskey]
    ns-verify-owner commit --key KEY.gskey      (prints the key's commitment and public key; verify --commitment HEX
                                                --public-key HEX checks them)

``verify`` renders N views of a run (its own cameras and sampled orbit poses) or reads the images of a folder,
decodes each view with the owner key's extractor, tests each view on its own against the binomial null
(``P(X >= m)`` for ``X ~ Binomial(48, 1/2)``), and combines the per-view decisions with the vote of
:func:`gsticker_plugin.metrics.combine_view_decisions` (never pooling bits across views). It prints the verdict
first, writes ``report.json`` and ``report.png``, and exits 0 ("owned"), 1 ("not shown") or 2 (error).

``calibrate`` decodes unmarked renders and images with a key and stores the observed null in the key (the key is
rewritten atomically; the previous file is kept as ``KEY.gskey.bak``). ``verify`` then uses the stricter of the
theoretical and the empirical per-view threshold and reports both. See docs/verify.md.

Three decoders (``--decode``): the blind *extractor* (the key's CNN reads RGB renders or images), the informed
*geometric* decoder (gsticker_plugin.decoders.geometric: fits the key's sticker to a suspect model's accumulation/depth against
the owner's unwatermarked base run; models only) and the informed *image* decoder (gsticker_plugin.decoders.image:
the same fit on the colour of images taken at known cameras, ``--images DIR --cameras transforms.json``). ``export-key`` adds the geometric decoder's reference (sticker,
gates) to a version-1 key from the watermarked run it belongs to.
"""

from __future__ import annotations

import sys
import traceback
from pathlib import Path
from typing import Optional, Sequence

import tyro

from gsticker_plugin import compat
from gsticker_plugin.errors import GStickerError, print_error
from gsticker_plugin.verify.configs import (  # noqa: F401 (the exit statuses are part of the command)
    EXIT_ERROR,
    EXIT_NOT_SHOWN,
    EXIT_OWNED,
    CalibrateConfig,
    CommitConfig,
    ExportKeyConfig,
    VerifyConfig,
)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``), run, and return the exit status (0 owned, 1 not shown, 2 error)."""

    # numpy scalars in keys/checkpoints (optimizer lr) under weights_only=True; offline-safe LPIPS for stock models
    compat.apply()
    argv = list(sys.argv[1:] if argv is None else argv)
    sub = "verify"
    if argv and argv[0] in ("verify", "calibrate", "export-key", "commit"):
        sub, argv = argv[0], argv[1:]
    try:
        if sub == "calibrate":
            cfg = tyro.cli(CalibrateConfig, args=argv, prog="ns-verify-owner calibrate")
        elif sub == "export-key":
            cfg = tyro.cli(ExportKeyConfig, args=argv, prog="ns-verify-owner export-key")
        elif sub == "commit":
            cfg = tyro.cli(CommitConfig, args=argv, prog="ns-verify-owner commit")
        else:
            cfg = tyro.cli(
                VerifyConfig,
                args=argv,
                prog="ns-verify-owner [verify]",
                description=(VerifyConfig.__doc__ or "") + "\n\nSubcommands: verify (default), calibrate "
                "(ns-verify-owner calibrate --help), export-key (adds the geometry reference to a "
                "version-1 key), commit (prints the key's commitment to publish at release).",
            )
    except SystemExit as e:  # --help (0) or a parse error (tyro prints it; status 2)
        return int(e.code) if isinstance(e.code, int) else EXIT_ERROR
    # deferred: the commands pull in Nerfstudio (seconds, and its warnings): parse the arguments first
    from gsticker_plugin.verify.calibrate import calibrate, calibrate_text
    from gsticker_plugin.verify.check import verify
    from gsticker_plugin.verify.keys import commit, export_key
    from gsticker_plugin.verify.report import summary_text

    try:
        if sub == "calibrate":
            res = calibrate(cfg)
            print(calibrate_text(res))
            return 0
        if sub == "commit":
            res = commit(cfg)
            print(res["commitment"])
            if res["public_key"]:
                print(res["public_key"])
            print(
                f"commitment of {res['key']}"
                + (" (first line) and the owner's public key (second line)" if res["public_key"] else "")
                + ": publish or timestamp them when you release the model; later `ns-verify-owner --key "
                f"{res['key']} --commitment HEX"
                + (" --public-key HEX" if res["public_key"] else "")
                + " ...` shows this key existed then"
                + (" and was signed by that identity" if res["public_key"] else ""),
                file=sys.stderr,
            )
            for c in res["null_caveats"]:
                print(f"note: weaker claim: {c}", file=sys.stderr)
            return 0
        if sub == "export-key":
            res = export_key(cfg)
            print(
                f"wrote {res['key']}: geometry reference of {res['run']} (fields {', '.join(res['fields'])})"
                + (f"; previous key kept as {res['backup']}" if res["backup"] else "")
            )
            return 0
        status, report = verify(cfg)
        print(summary_text(report))
        return status
    except GStickerError as e:
        return print_error(str(e))
    except KeyboardInterrupt:
        return print_error("interrupted; no verdict")
    except MemoryError:
        return print_error("out of memory while decoding; lower --max-side or --num-views")
    except Exception as e:  # a crash is never a verdict: one line, exit 2
        frames = traceback.extract_tb(e.__traceback__)
        where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
        return print_error(
            f"no verdict: {type(e).__name__}: {e}{where} (a failure inside ns-verify-owner, not a "
            "negative verdict; rerun with the same inputs to reproduce and report it)"
        )


def entrypoint() -> None:
    """Console script ``ns-verify-owner``."""
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
