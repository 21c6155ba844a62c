"""The recipient's message recovery on shared runs (``python -m gsticker_plugin.bench.recipient``).

For each shared run (its ``config.yml``) and its owner key, the recipient's best least-squares recovery
(:mod:`gsticker_plugin.attacks.recipient`) of the owner's bits from the folded sticker, with per-bit patterns
regenerated from the run's ``machine.seed`` and from each of ``--seeds`` other seeds (the fit with the smallest
residual is kept), beside the owner's control: the same fit with the patterns of the key's secret sticker seed.
Writes a Markdown page and its JSON.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Tuple

import tyro

from gsticker_plugin.bench import command_lines
from gsticker_plugin.machine import machine_info


@dataclass
class Args:
    runs: Tuple[Path, ...]
    """Shared runs: their config.yml."""
    keys: Tuple[Path, ...]
    """The owner key of each run, in the same order."""
    seeds: int = 8
    """Seeds 0..N-1 tried beside each run's machine.seed."""
    output: Path = Path("docs/bench-recipient.md")
    """The page (its JSON is written beside it)."""
    labels: Tuple[str, ...] = field(default_factory=tuple)
    """A label per run (default: the run folder's experiment name)."""


def attack_run(config: Path, key_path: Path, seeds: int) -> Dict[str, Any]:
    from gsticker_plugin.attacks import recipient as R
    from gsticker_plugin.key import OwnerKey
    from gsticker_plugin.model import seeded_sticker
    from gsticker_plugin.runs import latest_checkpoint, load_checkpoint_state, load_run_config

    key = OwnerKey.load(key_path)
    state = load_checkpoint_state(latest_checkpoint(Path(config).parent / "nerfstudio_models"))["pipeline"]
    folded = R.folded_last_layer(state)
    machine_seed = int(load_run_config(config).machine.seed)
    with contextlib.redirect_stdout(sys.stderr):
        candidates = [(s, R.regenerated_patterns(config, s)) for s in [machine_seed, *range(seeds)]]
    at_seed = R.recover_bits(folded, candidates[0][1])
    best = R.best_recovery(folded, candidates)
    geo = key.geometry or {}
    control = R.recover_bits(folded, seeded_sticker(geo["sticker_config"], int(geo["sticker_seed"])).mlp[-1].weight)
    return {
        "machine_seed": machine_seed,
        "at_machine_seed": R.matches(at_seed.bits, key.message),
        "best": R.matches(best.bits, key.message),
        "best_seed": best.seed,
        "best_residual": best.residual,
        "owner_control": R.matches(control.bits, key.message),
        "owner_control_residual": control.residual,
    }


def page(res: Dict[str, Any], args: Args) -> str:
    rows = res["rows"]
    best = [r["best"] for r in rows]
    mean = sum(best) / len(best)
    lines = [
        *command_lines(
            "The recipient's message recovery from shared runs",
            res["date"],
            args.output.with_suffix(".json").name,
            res["command"],
        ),
        "A recipient holds the shared run (config.yml and checkpoint). The folded sticker's output weights are the "
        "owner's message mixed with the per-bit patterns; the recipient regenerates the patterns as the sticker was "
        f"initialised from the run's `machine.seed` and from seeds 0-{args.seeds - 1}, and keeps the least-squares "
        "fit with the smallest residual (`gsticker_plugin.attacks.recipient`). The owner's control column is the "
        "same fit with the patterns of the key's secret sticker seed: what the recipient would read if that seed "
        "leaked.",
        "",
        "| run | recipient at machine.seed | recipient, best fit (seed) | owner's control (secret seed) |",
        "|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['at_machine_seed']}/48 | {r['best']}/48 (seed {r['best_seed']}, residual "
            f"{r['best_residual']:.2f}) | {r['owner_control']}/48 (residual {r['owner_control_residual']:.3f}) |"
        )
    lines += [
        "",
        f"Recipient's best recovery over {len(rows)} runs: mean {mean:.1f}/48, min {min(best)}, max {max(best)}, "
        f"{sum(b >= 36 for b in best)} at 36 or more (chance: Binomial(48, 1/2), mean 24, sd 3.5). Owner's control: "
        f"mean {sum(r['owner_control'] for r in rows) / len(rows):.1f}/48.",
        "",
    ]
    return "\n".join(lines)


def main(args: Args) -> None:
    if len(args.runs) != len(args.keys):
        raise SystemExit("error: pass one --keys entry per --runs entry")
    os.environ.setdefault("GSTICKER_NO_DOWNLOAD", "1")
    t0 = time.time()
    rows = []
    for i, (cfg, key) in enumerate(zip(args.runs, args.keys)):
        label = args.labels[i] if i < len(args.labels) else Path(cfg).parents[2].name
        rows.append({"label": label, "config": str(cfg), **attack_run(cfg, key, args.seeds)})
        print(f"{label}: {rows[-1]}", file=sys.stderr)
    res = {
        "command": "python -m gsticker_plugin.bench.recipient " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_info(),
        "seconds": time.time() - t0,
        "rows": rows,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n")
    args.output.write_text(page(res, args))
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main(tyro.cli(Args))
