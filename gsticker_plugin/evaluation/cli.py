"""``ns-gsticker-eval --config method_configs/eval/lego100.yaml``: run the evaluation protocol, resumably.

Writes ``OUTPUT_DIR/results.json``, ``results.md`` (tables beside the paper's numbers) and ``charts/*.png``.
Every stage is skipped when its output exists; ``--redo STAGE ...`` recomputes stages. Bad input: one line
``error: ...`` on stderr, exit status 2.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Tuple

import tyro

from gsticker_plugin import compat
from gsticker_plugin.errors import GStickerError, run_command
from gsticker_plugin.evaluation.config import ALL_STAGES, load_protocol


@dataclass
class EvalArgs:
    """Run the GeometrySticker evaluation protocol of a YAML file (method_configs/eval/*.yaml)."""

    config: Path
    """Protocol YAML, e.g. method_configs/eval/lego100.yaml (relative paths inside it: from the current folder)."""
    output_dir: Optional[Path] = None
    """Override the protocol's output_dir."""
    data: Optional[Path] = None
    """Override the protocol's scene with this dataset folder."""
    sticker_seeds: Optional[Tuple[int, ...]] = None
    """Override sticker.seeds: train the primary sticker again with these seeds (stage seeds), e.g. --sticker-seeds 1 2."""
    stages: Tuple[str, ...] = ALL_STAGES
    """Stages to run (in protocol order): scene bases sticker renders quality geometry seeds distortions curves
    recolor purify false_positives speed wild report."""
    redo: Tuple[str, ...] = ()
    """Stages to recompute even when their outputs exist (cached renders and trained runs are kept)."""
    progress: bool = True
    """tqdm progress bars on stderr."""


def main(args: EvalArgs) -> int:
    """Run the protocol's stages into its output folder; 0 when done."""
    compat.apply()  # the plugin's host fixes (offline LPIPS, checkpoint types)

    # nerfstudio 1.1.5's camera indexing warns on every render with this torch: noise in a long log
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")

    bad = [s for s in (*args.stages, *args.redo) if s not in ALL_STAGES]
    if bad:
        raise GStickerError(f"unknown stage(s) {', '.join(bad)}; use {' '.join(ALL_STAGES)}")
    # deferred: the stages pull in Nerfstudio (seconds): check the arguments first
    from gsticker_plugin.evaluation.runner import Runner

    protocol = load_protocol(args.config, output_dir=args.output_dir, data=args.data, sticker_seeds=args.sticker_seeds)
    runner = Runner(protocol, progress=args.progress, redo=args.redo, log=lambda m: print(m, flush=True))
    runner.run(args.stages)
    out = Path(protocol.output_dir)
    print(f"[eval] results: {out / 'results.json'}")
    if "report" in args.stages:
        print(f"[eval] tables:  {out / 'results.md'}")
        print(f"[eval] charts:  {out / 'charts'}")
    return 0


def run(argv: Optional[Sequence[str]] = None) -> int:
    args = tyro.cli(EvalArgs, args=None if argv is None else list(argv), description=__doc__.split("\n\n")[0])
    return run_command(lambda: main(args))


def entrypoint() -> None:
    raise SystemExit(run())


if __name__ == "__main__":
    entrypoint()
