"""The field mark on a real base (``python -m gsticker_plugin.bench.fieldmark``): a stock nerfacto run that carries the
message in its own hash table, read back from its geometry.

For each amplitude the base's hash table is marked (:mod:`gsticker_plugin.fieldmark`; the per-bit patterns and the
message drawn from ``--seed``) and written as a stock run of the base's method (its config.yml relocated, its
checkpoint with the one table replaced), which is then loaded like any suspect run (``runs.load_run``). On every
``--every``-th test view the informed fit reads the bits from that run's geometry against the base's; unmarked
models given with ``--null`` are read the same way. Writes a Markdown page and its JSON.
"""

from __future__ import annotations

import contextlib
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Tuple

import torch
import tyro

from gsticker_plugin.bench import command_lines, provenance, write_page
from gsticker_plugin.machine import config_under, recolor_into

TABLE_KEY = "_model.field.mlp_base.model.0.hash_table"


@dataclass
class Args:
    base: Path
    """The base run's config.yml (nerfacto, torch implementation)."""
    data: Path
    """Its dataset folder."""
    work_dir: Path = Path("outputs/bench-fieldmark")
    """Where the marked stock runs are written."""
    amplitudes: Tuple[float, ...] = (0.005, 0.01, 0.02)
    levels: Tuple[int, ...] = (0, 1, 2, 3)
    """Hash-table levels the per-bit patterns live on."""
    every: int = 8
    """Read every this-many-th test view (200 test views: 25)."""
    seed: int = 20261206
    """Patterns and message (a bench draws them from a seed; ns-train would draw them with `secrets`)."""
    null: Tuple[Path, ...] = ()
    """Unmarked runs of the same scene (config.yml) read with the same key."""
    recolor: Tuple[str, ...] = ()
    """ns-recolor edits of the first amplitude's marked run, read like it: each `SUBCOMMAND:ARG ARG`, e.g.
    'palette:--set 0=blue' 'hue:--shift 0.25'."""
    output: Path = Path("docs/experiments/bench-fieldmark.md")


def write_marked_run(base_cfg: Path, table, work: Path, name: str) -> Path:
    """A stock run of the base's method whose checkpoint is the base's with ``table`` as its field's hash table."""
    from gsticker_plugin.runs import latest_checkpoint, load_checkpoint_state, load_run_config, relocate
    from gsticker_plugin.shared import write_run

    config = load_run_config(base_cfg)
    run_dir = relocate(config, work, name, config.method_name, "run")
    state = load_checkpoint_state(latest_checkpoint(Path(base_cfg).parent / "nerfstudio_models"))
    if TABLE_KEY not in state["pipeline"]:
        raise SystemExit(f"error: {base_cfg}'s checkpoint has no {TABLE_KEY} (not a torch nerfacto run)")
    state["pipeline"][TABLE_KEY] = table.detach().clone()
    return write_run(config, state, run_dir)


def measure(args: Args) -> Dict[str, Any]:
    from gsticker_plugin import fieldmark as FM
    from gsticker_plugin import metrics
    from gsticker_plugin.decoders.fieldmark import decode_view
    from gsticker_plugin.decoders.fit import tie_generator
    from gsticker_plugin.runs import load_run

    dev = torch.device("cpu")
    with contextlib.redirect_stdout(sys.stderr):
        _, base_pipe, _ = load_run(args.base, data=args.data, device=dev)
    base = base_pipe.model
    encoder, _ = FM.parts(base.field)
    table = encoder.hash_table.data.clone()
    pats = FM.patterns(table.shape, encoder.hash_table_size, args.levels, 48, args.seed)
    message = torch.randint(0, 2, (48,), generator=torch.Generator().manual_seed(args.seed + 1))
    suspects: List[Tuple[str, Any]] = []
    marked_runs = {}
    for a in args.amplitudes:
        cfg = write_marked_run(args.base, FM.marked_table(table, pats, FM.signs_of(message), a), args.work_dir, f"a{a}")
        marked_runs[a] = cfg
        with contextlib.redirect_stdout(sys.stderr):
            _, pipe, _ = load_run(cfg, data=args.data, device=dev)
        assert type(pipe.model) is type(base)  # a stock model of the base's method
        suspects.append((f"marked a={a}", pipe.model, a))
    for i, edit in enumerate(args.recolor):
        sub, _, rest = edit.partition(":")
        dest = args.work_dir / f"recolor{i}"
        recolor_into(
            [sub, *rest.split()], marked_runs[args.amplitudes[0]], dest, args.work_dir / f"recolor{i}.log", what=edit
        )
        with contextlib.redirect_stdout(sys.stderr):
            _, pipe, _ = load_run(config_under(dest), data=args.data, device=dev)
        suspects.append((f"marked a={args.amplitudes[0]}, ns-recolor {sub} {rest}", pipe.model, args.amplitudes[0]))
    for n in args.null:
        with contextlib.redirect_stdout(sys.stderr):
            run_cfg, pipe, _ = load_run(n, data=args.data, device=dev)
        suspects.append((f"unmarked {run_cfg.method_name} ({n.parent.name})", pipe.model, None))
    cams = base_pipe.datamanager.eval_dataset.cameras
    views = list(range(0, len(cams), args.every))
    rows: List[Dict[str, Any]] = []
    gen = tie_generator(args.seed)
    for vi in views:
        t0 = time.time()
        fv = FM.field_view(base, cams[vi : vi + 1], pats)
        t_view = time.time() - t0
        with torch.no_grad():
            base_rgb = base.get_outputs_for_camera(cams[vi : vi + 1])["rgb"]
        for label, model, a in suspects:
            t1 = time.time()
            with torch.no_grad():
                out = model.get_outputs_for_camera(cams[vi : vi + 1])
            amp = a if a is not None else args.amplitudes[len(args.amplitudes) // 2]
            bits, fit = decode_view(fv, out, amp, gen)
            rows.append(
                {
                    "view": vi,
                    "suspect": label,
                    "matches": int((bits == message).sum()),
                    "explained": fit.explained,
                    "psnr_vs_base": float(metrics.psnr(out["rgb"].permute(2, 0, 1), base_rgb.permute(2, 0, 1))),
                    "seconds_features": t_view,
                    "seconds_decode": time.time() - t1,
                }
            )
        print(
            f"view {vi}: " + ", ".join(f"{r['suspect']} {r['matches']}" for r in rows[-len(suspects) :]),
            file=sys.stderr,
        )
    return {"views": views, "rows": rows, "suspects": [s[0] for s in suspects]}


def page(res: Dict[str, Any], args: Args) -> str:
    lines = [
        *command_lines(
            "The field mark: the message in a stock nerfacto's own hash table",
            res["date"],
            args.output.with_suffix(".json").name,
            res["command"],
        ),
        f"Base `{args.base}`; per-bit patterns on hash levels {list(args.levels)}; {len(res['views'])} test views "
        f"(every {args.every}th); a view passes at >= 41/48 (per-view FPR 1e-6). Each marked run is a stock run of the "
        "base's method (the base checkpoint with its field's hash table replaced), loaded like any suspect. "
        f"{res['machine']['cpu']}.",
        "",
        "| suspect | views passing | bit accuracy | matches min / median / max | fit explains (median) | PSNR vs base (dB) |",
        "|---|---|---|---|---|---|",
    ]
    for s in res["suspects"]:
        rs = [r for r in res["rows"] if r["suspect"] == s]
        m = sorted(r["matches"] for r in rs)
        ex = sorted(r["explained"] for r in rs)
        ps = [r["psnr_vs_base"] for r in rs]
        lines.append(
            f"| {s} | {sum(x >= 41 for x in m)}/{len(m)} | {100 * sum(m) / (48 * len(m)):.2f} % | "
            f"{m[0]} / {m[len(m) // 2]} / {m[-1]} | {100 * ex[len(ex) // 2]:.2f} % | {sum(ps) / len(ps):.2f} |"
        )
    lines += [
        "",
        "Seconds per view (the features, then each decode) are in the JSON; they are not quoted here unless the run "
        "had the machine alone.",
        "",
    ]
    return "\n".join(lines)


def main(args: Args) -> None:
    import os

    os.environ.setdefault("GSTICKER_NO_DOWNLOAD", "1")
    from gsticker_plugin import compat

    compat.apply()
    res = {**measure(args), **provenance("gsticker_plugin.bench.fieldmark")}
    write_page(args.output, res, lambda r: page(r, args))


if __name__ == "__main__":
    main(tyro.cli(Args))
