"""``ns-verify-owner``: does a suspect model, or a folder of suspect images, carry an owner's message?

Four subcommands, one dataclass each (:mod:`gsticker_plugin.verify.configs`) joined by a tyro Union; ``verify`` runs
when no subcommand is named::

    ns-verify-owner [verify] (--load-config RUN/config.yml | --images DIR) (--key KEY.gskey | --keys DIR) [...]
    ns-verify-owner calibrate --key KEY.gskey [--load-config RUN/config.yml ...] [--images DIR ...] [...]
    ns-verify-owner export-key --load-config WATERMARKED_RUN/config.yml --key KEY.gskey [--output NEW.gskey]
    ns-verify-owner commit --key KEY.gskey

``verify`` decodes views of the suspect with each key (:mod:`gsticker_plugin.verify.check`), tests each view on its
own against the binomial null, combines the per-view decisions by a vote, prints the verdict first, writes
``report.json`` and ``report.png``, and exits 0 ("owned"), 1 ("not shown") or 2 (error: one ``error:`` line, never
a verdict). ``calibrate`` stores a measured null in the key; ``commit`` prints what to publish at release. See
docs/verify.md.
"""

from __future__ import annotations

import sys
from typing import Callable, Dict, Optional, Sequence, Union

import tyro
from typing_extensions import Annotated

from gsticker_plugin import compat
from gsticker_plugin.errors import run_command
from gsticker_plugin.verify.configs import (  # noqa: F401 (the exit statuses are part of the command)
    EXIT_ERROR,
    EXIT_NOT_SHOWN,
    EXIT_OWNED,
    CalibrateConfig,
    CommitConfig,
    ExportKeyConfig,
    VerifyConfig,
)

SUBCOMMANDS = ("verify", "calibrate", "export-key", "commit")

Commands = Union[
    Annotated[VerifyConfig, tyro.conf.subcommand(name="verify")],
    Annotated[CalibrateConfig, tyro.conf.subcommand(name="calibrate")],
    Annotated[ExportKeyConfig, tyro.conf.subcommand(name="export-key")],
    Annotated[CommitConfig, tyro.conf.subcommand(name="commit")],
]
"""One dataclass per subcommand; ``verify`` is also what runs when no subcommand is named."""


def run_verify(cfg: VerifyConfig) -> int:
    from gsticker_plugin.verify.check import verify
    from gsticker_plugin.verify.report import summary_text

    status, report = verify(cfg)
    print(summary_text(report))
    return status


def run_calibrate(cfg: CalibrateConfig) -> int:
    from gsticker_plugin.verify.calibrate import calibrate, calibrate_text

    print(calibrate_text(calibrate(cfg)))
    return 0


def run_commit(cfg: CommitConfig) -> int:
    from gsticker_plugin.verify.keys import commit

    res = commit(cfg)
    signed = bool(res["public_key"])
    print(res["commitment"])
    if signed:
        print(res["public_key"])
    print(
        f"commitment of {res['key']}"
        + (" (first line) and the owner's public key (second line)" if signed else "")
        + ": publish or timestamp them when you release the model; later `ns-verify-owner --key "
        f"{res['key']} --commitment HEX"
        + (" --public-key HEX" if signed else "")
        + " ...` shows this key existed then"
        + (" and was signed by that identity" if signed else ""),
        file=sys.stderr,
    )
    for c in res["null_caveats"]:
        print(f"note: weaker claim: {c}", file=sys.stderr)
    return 0


def run_export_key(cfg: ExportKeyConfig) -> int:
    from gsticker_plugin.verify.keys import export_key

    res = export_key(cfg)
    print(
        f"wrote {res['key']}: geometry reference of {res['run']} (fields {', '.join(res['fields'])})"
        + (f"; previous key kept as {res['backup']}" if res["backup"] else "")
    )
    return 0


RUNNERS: Dict[type, Callable] = {
    VerifyConfig: run_verify,
    CalibrateConfig: run_calibrate,
    CommitConfig: run_commit,
    ExportKeyConfig: run_export_key,
}


def parse(argv: Sequence[str]) -> Union[VerifyConfig, CalibrateConfig, ExportKeyConfig, CommitConfig]:
    """The subcommand's config from ``argv``; arguments that name no subcommand are ``verify``'s."""
    argv = list(argv)
    if argv[:1] and argv[0] not in SUBCOMMANDS and argv[0] not in ("-h", "--help"):
        argv = ["verify", *argv]
    return tyro.cli(Commands, args=argv, prog="ns-verify-owner", description=__doc__.split("\n\n")[0])  # type: ignore[call-overload]


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``), run, and return the exit status (0 owned, 1 not shown, 2 error)."""
    compat.apply()  # numpy scalars in keys/checkpoints under weights_only=True; offline-safe LPIPS for stock models
    try:
        cfg = parse(sys.argv[1:] if argv is None else argv)
    except SystemExit as e:  # --help (0) or a parse error (tyro prints it; status 2)
        return int(e.code) if isinstance(e.code, int) else EXIT_ERROR
    return run_command(lambda: RUNNERS[type(cfg)](cfg), crash="no verdict")


def entrypoint() -> None:
    """Console script ``ns-verify-owner``."""
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
