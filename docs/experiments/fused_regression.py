"""Experiment (issue 42, a route that was stopped): fuse the sticker into a stock nerfacto by regressing its density.

Teacher: the shared lego0 run of `python -m gsticker_plugin.bench.recipient --work-dir outputs/bench-recipient ...`
(the lego100 nerfacto-small base + a 300-step folded sticker). Student: the base nerfacto; only field.mlp_base (hash
grid + density MLP) is trained at the final field's samples of 48 views, the base's geo features held. Targets:
`loss=logdensity` (the mark's log-density ratio) or `loss=alpha` (transmittance-weighted alpha). Evaluated with the
geometric decoder on 8 test views and by PSNR. Run from the repository root, e.g.

    python docs/experiments/fused_regression.py steps=1500 lr=3e-3 tag=a loss=logdensity
    python docs/experiments/fused_regression.py steps=1500 lr=1e-3 tag=b loss=alpha

Writes outputs/exp42/TAG/log.txt and result.json. Kept out of the package: the route read 31-36/48 and was replaced by
the field mark (gsticker_plugin/fieldmark.py).
"""

import json
import math
import sys
import time
from pathlib import Path

import torch
from nerfstudio.cameras.rays import Frustums, RaySamples

from gsticker_plugin import compat
from gsticker_plugin.decoders.geometric import decode_suspect
from gsticker_plugin.decoders.reference import load_base_reference
from gsticker_plugin.fastpath import cache_view, novel_cameras
from gsticker_plugin.key import OwnerKey
from gsticker_plugin.runs import load_run

compat.apply()
torch.manual_seed(0)
ARGS = dict(a.split("=") for a in sys.argv[1:])
STEPS = int(ARGS.get("steps", 1500))
LR = float(ARGS.get("lr", 3e-3))
BATCH = int(ARGS.get("batch", 32768))
GEO = float(ARGS.get("geo", 1.0))
VIEWS = int(ARGS.get("views", 48))
TAG = ARGS.get("tag", "a")
OUT = Path("outputs/exp42") / TAG
OUT.mkdir(parents=True, exist_ok=True)
log = open(OUT / "log.txt", "w")


def say(*a):
    print(*a, flush=True)
    print(*a, file=log, flush=True)


W = Path("outputs/bench-recipient")
DATA = Path("../shared/data/lego100")
dev = torch.device("cpu")
_, wm, _ = load_run(W / "runs/lego0/geometrysticker/run/config.yml", data=DATA, device=dev)
model = wm.model
key = OwnerKey.load(W / "keys/lego0.gskey")
wrap = model.final_wrap
model.wrap_state.folded = model.folded_sticker
field_t = model.base.field
avg = float(field_t.average_init_density)
mu = float(wrap.gate.mu)

# ------------------------------------------------------------------ samples of many views
t0 = time.time()
cams = wm.datamanager.train_dataset.cameras
gen = torch.Generator().manual_seed(777)
pool_cams = [cams[i : i + 1] for i in torch.randperm(len(cams), generator=gen)[: VIEWS // 2].tolist()]
nov = novel_cameras(cams, VIEWS - len(pool_cams), gen)
pool_cams += [nov[i : i + 1] for i in range(nov.shape[0])]
P, TPRE, OPEN, DT, TT, TAL = [], [], [], [], [], []
with torch.no_grad():
    for cam in pool_cams:
        v = cache_view(model, cam, True, min_density=1e-4 * mu, full_precision=True)
        dens = v.density  # base density [A S 1]
        trans = torch.exp(-torch.cumsum(dens * v.deltas, dim=-2) + dens * v.deltas)  # light reaching each sample
        keep = trans[..., 0] > 1e-4
        pos = v.positions.float()[keep]
        d = dens[keep]
        delta, psi = wrap.delta(d, pos, None)
        marked = torch.relu(d + delta)
        DT.append(v.deltas[keep])
        TT.append(trans[keep])
        TAL.append(1 - torch.exp(-marked * v.deltas[keep]))
        P.append(pos)
        TPRE.append(torch.log((marked / d.clamp_min(1e-12)).clamp_min(1e-3)))  # the mark's log-density ratio
        OPEN.append((delta.abs() > 0).reshape(-1))
P, TPRE, OPEN = torch.cat(P), torch.cat(TPRE), torch.cat(OPEN)
DT, TT, TAL = torch.cat(DT), torch.cat(TT), torch.cat(TAL)
LOSS = ARGS.get("loss", "alpha")
say(f"pool: {len(pool_cams)} views, {P.shape[0]} samples, {int(OPEN.sum())} open, {time.time() - t0:.0f} s")

# ------------------------------------------------------------------ student
_, student_pipe, _ = load_run(
    Path("../shared/checkpoints/lego100-nerfacto-small/nerfacto/base/config.yml"), data=DATA, device=dev
)
student = student_pipe.model
fs = student.field


def density_head(positions):
    n = positions.shape[0]
    fr = Frustums(
        origins=positions[:, None],
        directions=torch.zeros(n, 1, 3),
        starts=torch.zeros(n, 1, 1),
        ends=torch.zeros(n, 1, 1),
        pixel_area=torch.ones(n, 1, 1),
    )
    rs = RaySamples(frustums=fr)
    dens, geo = fs.get_density(rs)
    if LOSS == "alpha":
        return dens.reshape(n, 1), geo.reshape(n, -1)
    return fs._density_before_activation.reshape(n, 1), geo.reshape(n, -1)


with torch.no_grad():
    GEO0 = torch.cat([density_head(P[i : i + 65536])[1] for i in range(0, P.shape[0], 65536)])
    PRE0 = torch.cat([density_head(P[i : i + 65536])[0] for i in range(0, P.shape[0], 65536)])
    if LOSS == "alpha":
        A0 = 1 - torch.exp(-PRE0 * DT)
        say(
            f"mark in transmittance-weighted alpha at open samples: rms {float(((TAL - A0) * TT)[OPEN].pow(2).mean().sqrt()):.3g}"
        )
    else:
        say(f"mark in log-density at open samples: rms {float(TPRE[OPEN].pow(2).mean().sqrt()):.3g}")
        TPRE = PRE0 + TPRE * OPEN[:, None].float()

for p in student.parameters():
    p.requires_grad_(False)
params = list(fs.mlp_base.parameters())
for p in params:
    p.requires_grad_(True)
opt = torch.optim.Adam(params, lr=LR, eps=1e-15)
sched = torch.optim.lr_scheduler.ExponentialLR(opt, (0.1) ** (1 / STEPS))
open_idx = OPEN.nonzero().squeeze(-1)
curve = []
t0 = time.time()
for step in range(STEPS):
    a = open_idx[torch.randint(0, open_idx.numel(), (BATCH // 2,), generator=gen)]
    b = torch.randint(0, P.shape[0], (BATCH // 2,), generator=gen)
    idx = torch.cat([a, b])
    pre, geo = density_head(P[idx])
    if LOSS == "alpha":
        al = 1 - torch.exp(-pre * DT[idx])
        lp = ((al - TAL[idx]) * TT[idx]).pow(2).mean() * 100
    else:
        lp = (pre - TPRE[idx]).pow(2).mean()
    lg = (geo - GEO0[idx]).pow(2).mean()
    loss = lp + GEO * lg
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    sched.step()
    if step % 100 == 0 or step == STEPS - 1:
        with torch.no_grad():
            if LOSS == "alpha":
                e_open = float((((1 - torch.exp(-pre[: BATCH // 2] * DT[a])) - TAL[a]) * TT[a]).pow(2).mean().sqrt())
            else:
                e_open = float((pre[: BATCH // 2] - TPRE[a]).pow(2).mean().sqrt())
        curve.append({"step": step, "s": time.time() - t0, "pre": float(lp), "geo": float(lg), "open_rms": e_open})
        say(curve[-1])
for p in params:
    p.requires_grad_(False)

# ------------------------------------------------------------------ evaluate
ref = load_base_reference(key, W / "keys/lego0.gskey", None, DATA, dev)
test = student_pipe.datamanager.eval_dataset.cameras
n_eval = int(ARGS.get("eval", 8))
step = max(1, len(test) // n_eval)
cams_eval = [(f"test/{i:03d}", test[i : i + 1]) for i in range(0, len(test), step)][:n_eval]
t0 = time.time()
dec, _ = decode_suspect(key, ref, student, n_eval, 0.0, 0, cameras=cams_eval, full_renders=False)
m = [int(x) for x in dec["matches"]]
say(f"geometric decoder on {len(m)} test views: matches {m}, {time.time() - t0:.0f} s")
ps_base, ps_wm, ps_gt = [], [], []
with torch.no_grad():
    for name, cam in cams_eval[:4]:
        s_rgb = student.get_outputs_for_camera(cam)["rgb"]
        w_rgb = model.get_outputs_for_camera(cam)["rgb"]
        with model.sticker_enabled(False):
            b_rgb = model.get_outputs_for_camera(cam)["rgb"]
        ps_base.append(-10 * math.log10(float((s_rgb - b_rgb).pow(2).mean())))
        ps_wm.append(-10 * math.log10(float((s_rgb - w_rgb).pow(2).mean())))
say(f"PSNR fused vs base {sum(ps_base) / len(ps_base):.2f} dB, fused vs watermarked {sum(ps_wm) / len(ps_wm):.2f} dB")
(OUT / "result.json").write_text(
    json.dumps({"args": ARGS, "curve": curve, "matches": m, "psnr_vs_base": ps_base, "psnr_vs_wm": ps_wm}, indent=1)
)
