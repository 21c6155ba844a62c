"""The recipient's message recovery on shared runs (``python -m gsticker_plugin.bench.recipient``).

For each shared run (its ``config.yml``; ``--work-dir`` trains them first with ``ns-train``) and its owner key, the
recipient's recovery (:mod:`gsticker_plugin.attacks.recipient`) of the owner's bits, with per-bit patterns
regenerated from the run's ``machine.seed`` and from each of ``--seeds`` other seeds, beside the owner's control:
the same reading with the key's secret seed. ``--mark sticker``: least squares on the folded sticker (the fit with
the smallest residual is kept). ``--mark field``: the sign of the shared hash table's correlation with each pattern
(the best of the guesses is the one that reads the most bits, an upper bound on what the recipient can pick).
Writes a Markdown page and its JSON.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import tyro

from gsticker_plugin.bench import TINY_POOL, command_lines, provenance, write_page
from gsticker_plugin.machine import config_under, run_logged
from gsticker_plugin.runs import latest_checkpoint


@dataclass
class Args:
    runs: Tuple[Path, ...] = ()
    """Shared runs: their config.yml (besides those of --work-dir)."""
    keys: Tuple[Path, ...] = ()
    """The owner key of each --runs entry, in the same order."""
    work_dir: Optional[Path] = None
    """Train the runs here first (missing ones only): --tiny sticker runs of 10 steps on a generated 32 px scene and
    --lego runs of 300 steps on --lego-checkpoint, each with its own secret sticker seed and message."""
    tiny: int = 10
    lego: int = 2
    lego_checkpoint: Optional[Path] = None
    """The base checkpoint of the lego runs (e.g. the shared lego100 nerfacto-small base's step-000002999.ckpt)."""
    lego_data: Optional[Path] = None
    """Its dataset folder."""
    seeds: int = 8
    """Seeds 0..N-1 tried beside each run's machine.seed."""
    mark: Literal["sticker", "field"] = "sticker"
    """The mark of the runs: a folded sticker, or the field mark in a nerfacto hash table."""
    output: Path = Path("docs/experiments/bench-recipient.md")
    """The page (its JSON is written beside it)."""


TINY_STICKER = ["--max-num-iterations", "10", *TINY_POOL]
HEADS_OFF = ["--pipeline.msg-weight", "0", "--pipeline.negative-weight", "0", "--pipeline.cls-weight", "0"]
CPU = ["--machine.device-type", "cpu", "--vis", "tensorboard"]


def make_runs(args: Args) -> List[Tuple[str, Path, Path]]:
    """Train the missing runs under ``args.work_dir`` with ``ns-train``; (label, config.yml, key) of each."""
    work = Path(args.work_dir)
    keys = work / "keys"
    keys.mkdir(parents=True, exist_ok=True)
    os.environ["GSTICKER_KEYS_DIR"] = str(keys)  # the owner identity of these runs lives beside their keys
    train = str(Path(sys.executable).parent / "ns-train")
    out: List[Tuple[str, Path, Path]] = []

    def sticker(label: str, ckpt: Path, extra: List[str]) -> None:
        key = keys / f"{label}.gskey"
        if not key.is_file():
            cmd = [train, "geometrysticker", "--pipeline.mark", args.mark, "--load-checkpoint", str(ckpt), *CPU]
            cmd += ["--output-dir", str(work / "runs")]
            cmd += ["--experiment-name", label, "--timestamp", "run", "--pipeline.key-path", str(key), *extra]
            run_logged(cmd, work / f"{label}.log", what=f"sticker run {label}")
        out.append((label, config_under(work / "runs" / label), key))  # geometrysticker/ or the base's method

    if args.tiny:
        scene = work / "scene"
        if not (scene / "transforms_train.json").is_file():
            cmd = [sys.executable, "-m", "gsticker_plugin.scene", "--output-dir", str(scene), "--resolution", "32"]
            cmd += ["--num-train", "6", "--num-val", "2", "--num-test", "2", "--seed", "0"]
            run_logged(cmd, work / "scene.log", what="scene")
        base_models = work / "base" / "nerfacto" / "gsticker-nerfacto-small" / "base" / "nerfstudio_models"
        if latest_checkpoint(base_models) is None:
            cmd = [train, "gsticker-nerfacto-small", "--pipeline.model.num-nerf-samples-per-ray", "16"]
            cmd += ["--pipeline.model.num-proposal-samples-per-ray", "32", "16"]
            cmd += ["--pipeline.datamanager.train-num-rays-per-batch", "256", *CPU, "--output-dir", str(work / "base")]
            steps = "2" if args.mark == "sticker" else "100"  # the field mark lives in rows training moved
            cmd += ["--experiment-name", "nerfacto", "--timestamp", "base", "--max-num-iterations", steps]
            cmd += ["--steps-per-save", steps, "blender-data", "--data", str(scene)]
            run_logged(cmd, work / "base.log", what="tiny base")
        base = latest_checkpoint(base_models)
        for i in range(args.tiny):
            sticker(f"tiny{i}", base, TINY_STICKER if args.mark == "sticker" else [])
    if args.lego:
        if args.lego_checkpoint is None or args.lego_data is None:
            raise SystemExit("error: --lego runs need --lego-checkpoint and --lego-data")
        for i in range(args.lego):
            extra = ["--data", str(args.lego_data), "--max-num-iterations", "300", *HEADS_OFF]
            sticker(f"lego{i}", Path(args.lego_checkpoint), extra)
    return out


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


def attack_field_run(config: Path, key_path: Path, seeds: int) -> Dict[str, Any]:
    """The recipient's correlation reading of a field-marked nerfacto run at its machine.seed and seeds
    0..``seeds``-1, and the owner's control with the key's pattern seed."""
    from gsticker_plugin.attacks.recipient import field_mark_correlation, matches
    from gsticker_plugin.key import OwnerKey
    from gsticker_plugin.runs import latest_checkpoint, load_checkpoint_state, load_run_config

    key = OwnerKey.load(key_path)
    mark = key.field_mark or {}
    if mark.get("host", "hash") != "hash":
        raise SystemExit(f"error: {key_path} marks TensoRF planes; --mark field reads nerfacto hash tables")
    cfg = load_run_config(config)
    state = load_checkpoint_state(latest_checkpoint(Path(config).parent / "nerfstudio_models"))["pipeline"]
    table = state["_model.field.mlp_base.model.0.hash_table"]
    size = 2 ** int(cfg.pipeline.model.log2_hashmap_size)
    machine_seed = int(cfg.machine.seed)

    def read(seed: int) -> int:
        bits = field_mark_correlation(table, size, mark["levels"], seed, float(mark["init_scale"]), key.num_bits)
        return matches(bits, key.message)

    guesses = {s: read(s) for s in [machine_seed, *range(seeds)]}
    best_seed = max(guesses, key=lambda s: guesses[s])
    return {
        "machine_seed": machine_seed,
        "at_machine_seed": guesses[machine_seed],
        "best": guesses[best_seed],
        "best_seed": best_seed,
        "owner_control": read(int(mark["pattern_seed"])),
    }


def page(res: Dict[str, Any], args: Args) -> str:
    rows, field = res["rows"], args.mark == "field"
    if field:
        title, how = (
            "The recipient's message reading from field-marked shared runs",
            (
                "A recipient holds the shared run: a stock nerfacto whose hash table is the base's plus the owner's "
                "message mixed with per-bit patterns. Without the base's table, the recipient's reading of bit k is the "
                "sign of the shared table's correlation with pattern k, the patterns regenerated from a guessed seed: the "
                f"run's `machine.seed` and seeds 0-{args.seeds - 1}; the best guess is the one that reads the most bits "
                "(the recipient cannot tell which that is without the message: an upper bound). The owner's control "
                "reads the same way with the key's pattern seed: what the recipient would read if that seed leaked."
            ),
        )
        runs = (
            "10 tiny runs, `ns-train geometrysticker --pipeline.mark field` on a 100-step nerfacto base of a generated "
            "32 px scene, and lego100 runs on the shared nerfacto-small base; each draws its own message and pattern "
            "seed with `secrets`"
        )
    else:
        title, how = (
            "The recipient's message recovery from shared runs",
            (
                "A recipient holds the shared run (config.yml and checkpoint). The folded sticker's output weights are "
                "the owner's message mixed with the per-bit patterns. The recipient rebuilds the pipeline from the shared "
                "config as `ns-train` does after seeding every generator, with the sticker drawn from the global "
                "generator at its place in the build (how it was initialised before it had a secret seed of its own), at "
                f"the run's `machine.seed` and at seeds 0-{args.seeds - 1}, and keeps the least-squares fit with the "
                "smallest residual (`gsticker_plugin.attacks.recipient`). The owner's control column is the same fit with "
                "the patterns of the key's secret sticker seed: what the recipient would read if that seed leaked."
            ),
        )
        runs = (
            "10 tiny runs, `ns-train geometrysticker` for 10 steps on a 2-step nerfacto base of a generated 32 px "
            "scene, and lego100 runs of 300 steps on the shared nerfacto-small base (heads off); each draws its own "
            "message and sticker seed with `secrets`"
        )
    lines = [
        *command_lines(title, res["date"], args.output.with_suffix(".json").name, res["command"]),
        how,
        "",
        f"The runs (`--work-dir`): {runs}; `machine.seed` is the default, 42, in every one.",
        "",
        f"| run | recipient at machine.seed | recipient, best {'guess' if field else 'fit'} (seed) | owner's control "
        "(secret seed) |",
        "|---|---|---|---|",
    ]
    for r in rows:
        fit = "" if field else f", residual {r['best_residual']:.2f}"
        own = "" if field else f" (residual {r['owner_control_residual']:.3f})"
        lines.append(
            f"| {r['label']} | {r['at_machine_seed']}/48 | {r['best']}/48 (seed {r['best_seed']}{fit}) | "
            f"{r['owner_control']}/48{own} |"
        )
    best = [r["best"] for r in rows]
    lines += [
        "",
        f"Recipient's best over {len(rows)} runs: mean {sum(best) / len(best):.1f}/48, min {min(best)}, max "
        f"{max(best)}, {sum(b >= 36 for b in best)} at 36 or more (one reading is chance: Binomial(48, 1/2), mean "
        f"24, sd 3.5). Owner's control: mean {sum(r['owner_control'] for r in rows) / len(rows):.1f}/48.",
        "",
    ]
    return "\n".join(lines)


def main(args: Args) -> None:
    if len(args.runs) != len(args.keys):
        raise SystemExit("error: pass one --keys entry per --runs entry")
    os.environ.setdefault("GSTICKER_NO_DOWNLOAD", "1")
    t0 = time.time()
    todo = make_runs(args) if args.work_dir is not None else []
    todo += [(Path(c).parents[2].name, Path(c), Path(k)) for c, k in zip(args.runs, args.keys)]
    rows = []
    for label, cfg, key in todo:
        attack = attack_run if args.mark == "sticker" else attack_field_run
        rows.append({"label": label, "config": str(cfg), **attack(cfg, key, args.seeds)})
        print(f"{label}: {rows[-1]}", file=sys.stderr)
    res = {**provenance("gsticker_plugin.bench.recipient"), "seconds": time.time() - t0, "rows": rows}
    write_page(args.output, res, lambda r: page(r, args))


if __name__ == "__main__":
    main(tyro.cli(Args))
