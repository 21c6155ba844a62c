"""``ns-recolor``: recolor any Nerfstudio NeRF run (on CPU, one command); results open in the stock viewer.

    ns-recolor palette  --load-config RUN/config.yml --list                       # print the palette + swatch PNG
    ns-recolor palette  --load-config RUN/config.yml --output-dir OUT --set 2=#1E90FF 0=red
    ns-recolor palette  --load-config RUN/config.yml --output-dir OUT --palette keep blue keep yellow keep
    ns-recolor hue      --load-config RUN/config.yml --output-dir OUT --shift 0.25
    ns-recolor hue      --load-config RUN/config.yml --output-dir OUT --image-level --shift 0.5   # jittered renders
    ns-recolor finetune --load-config RUN/config.yml --output-dir OUT --set 0=blue --steps 300
    ns-recolor finetune --load-config RUN/config.yml --output-dir OUT --targets EDITED_IMAGES/ --steps 300

Bad input prints one line ``error: <problem and fix>`` on stderr and exits with status 2. The input run is
never changed; an existing ``--output-dir`` is refused unless ``--overwrite``. See docs/recolor.md.
"""

from __future__ import annotations

from typing import List, Optional, Union

import tyro
from typing_extensions import Annotated

from gsticker_plugin import compat
from gsticker_plugin.errors import run_command
from gsticker_plugin.recolor.configs import FinetuneArgs, HueArgs, PaletteArgs

Args = Union[
    Annotated[PaletteArgs, tyro.conf.subcommand("palette")],
    Annotated[HueArgs, tyro.conf.subcommand("hue")],
    Annotated[FinetuneArgs, tyro.conf.subcommand("finetune")],
]


def run(argv: Optional[List[str]] = None) -> int:
    """Parse ``argv`` and run; bad input -> one line ``error: ...`` on stderr, exit status 2."""
    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)
    args = tyro.cli(Args, args=argv, description=__doc__.split("\n\n")[0])
    # deferred: the edits pull in Nerfstudio (seconds): parse the arguments first
    from gsticker_plugin.recolor.edits import apply_edit

    status = run_command(lambda: apply_edit(args))
    if status:
        raise SystemExit(status)
    return status


def entrypoint() -> None:
    raise SystemExit(run())


if __name__ == "__main__":
    entrypoint()
