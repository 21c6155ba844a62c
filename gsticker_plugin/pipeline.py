"""GeometrySticker pipeline: trains the sticker, the gate, the extractor and the classifier on a frozen base.

The extractor and classifier (the *heads*) are the owner's secret: they are held outside the pipeline's
module tree, so they never enter the shareable checkpoint; the trainer writes them into the owner key.

With several processes (``--machine.num-devices N``) the model is not wrapped in DDP: every rank starts from rank 0's
sticker, gates and heads (:meth:`GeometryStickerPipeline.sync_from_rank0`), draws its own batches, and the trainer's
optimizers average the gradients over the ranks before each step (:meth:`GeometryStickerPipeline.average_gradients`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterable, List, Literal, Mapping, Optional, Sequence, Tuple, Type

import torch
import torch.distributed as dist
import torch.nn.functional as F
import tyro
from nerfstudio.data.datamanagers.base_datamanager import DataManagerConfig, VanillaDataManagerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils import comms
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import Progress
from torch import Tensor

from gsticker_plugin import hashgrid, metrics
from gsticker_plugin.attacks import RandomDistortion, RandomDistortionConfig
from gsticker_plugin.fastpath import (
    ViewCache,
    cache_view,
    camera_layout,
    condition_term,
    coverage,
    noise_variance,
    novel_cameras,
    pool_memory_mb,
    render_cached,
    sign_grams,
)
from gsticker_plugin.heads import HeadConfig, Heads, count_parameters
from gsticker_plugin.key import OwnerKey, message_from_owner_id, parse_message, random_message
from gsticker_plugin.model import GeometryStickerModel, GeometryStickerModelConfig, geometry_reference, shareable_state
from gsticker_plugin.runs import final_rgb
from gsticker_plugin.shared import DEFAULT_LEVELS
from gsticker_plugin.sticker import composite, sparsity_loss


@dataclass
class GeometryStickerPipelineConfig(VanillaPipelineConfig):
    """Owner message, losses and the training strategy of the sticker stage."""

    _target: Type = field(default_factory=lambda: GeometryStickerPipeline)
    datamanager: DataManagerConfig = field(default_factory=VanillaDataManagerConfig)
    """Replaced by the base run's data settings when training starts."""
    model: GeometryStickerModelConfig = field(default_factory=GeometryStickerModelConfig)
    heads: HeadConfig = field(default_factory=HeadConfig)
    """Extractor and classifier networks (the owner's secret)."""
    train_heads: bool = False
    """Sticker: train the extractor and classifier beside the sticker (the blind decoder reads them; the informed
    decoders do not). Off: they stay at their initialization and no step runs them."""
    owner_id: str = ""
    """A label for the owner, kept in the owner key only (reports name it); not the source of the bits."""
    message: Optional[str] = None
    """The message as 0/1 characters (default: drawn uniformly at random with `secrets`; the key records which)."""
    message_from_owner_id: bool = False
    """Derive the message from --pipeline.owner-id (sha256) instead of drawing it: weaker, anyone who knows the ID
    knows the bits; the key and the verification report say so."""
    message_source: tyro.conf.Suppress[str] = ""
    """How the message was drawn (random, owner-id, given); set by the trainer."""
    sticker_seed: Optional[int] = None
    """Seed of the sticker's initial weights (default: drawn with `secrets`). Kept in the owner key only, never in
    config.yml; give one only to reproduce a run, and keep it as secret as the message."""
    mark: Literal["auto", "field", "sticker"] = "auto"
    """What carries the message in the shared run. field: the base's own density field (its hash table, or TensoRF's
    density planes: the shared run is a stock run of the base's method, written in seconds; nerfacto bases with the
    torch implementation and TensoRF bases). sticker: a trained sticker (a geometrysticker run, heads and steps
    below). auto: field where the base hosts it (nerfacto with the torch implementation, TensoRF vector-matrix), else
    sticker. Pictures of a TensoRF shared run are not read yet: pass sticker to read a TensoRF run's pictures."""
    field_amplitude: Optional[float] = None
    """Field mark: amplitude of the per-bit patterns (default: 0.01 on a hash table, 50 dB render PSNR vs the base on
    lego100; 0.03 on TensoRF's density planes)."""
    field_levels: Tuple[int, ...] = DEFAULT_LEVELS
    """Field mark: the hash levels the per-bit patterns live on."""
    pattern_seed: Optional[int] = None
    """Field mark: seed of the per-bit patterns (default: drawn with `secrets`). Kept in the owner key only, never in
    config.yml; give one only to reproduce a run, and keep it as secret as the message."""
    key_path: Optional[Path] = None
    """Where the owner key is written (default: the per-user keys folder, $GSTICKER_KEYS_DIR or
    ~/.local/share/gsticker/keys/EXPERIMENT-METHOD-TIMESTAMP.gskey; never inside the run's output folder). Keep it
    secret."""
    base_run: tyro.conf.Suppress[Dict[str, Any]] = field(default_factory=dict)
    """Reference to the base run (method, config, checkpoint and its sha256); filled in automatically."""
    fast_path: bool = True
    """Train on cached base samples (True) or re-render the base every step (False, for comparison)."""
    pool_train_views: int = 48
    """Training cameras rendered into the fast-path pool."""
    pool_novel_views: int = 48
    """Novel cameras rendered into the pool (see ``novel_layout``)."""
    novel_layout: Literal["auto", "orbit", "capture"] = "auto"
    """How novel cameras are drawn: orbit (training cameras turned about the world z axis: an object in the middle),
    capture (between training cameras of a forward-facing capture), auto (chosen from the training cameras)."""
    monitor_views: int = 8
    """Held-out novel views on which bit accuracy is reported during training."""
    steps_per_monitor: int = 100
    """Report held-out bit accuracy every this many steps."""
    views_per_step: int = 4
    """Views (fast path) or patches (naive path) per step."""
    patch_size: int = 64
    """Naive path: side of the square ray patch rendered per view each step."""
    owner_message_prob: float = 0.0
    """Share of training renders that carry the owner's message; the rest carry uniformly random messages.
    Above 0 the extractor gains a prior toward the owner's bits (it would 'decode' them from clean images),
    so the default trains on random messages only: the extractor has to read the message, it cannot print one."""
    distortion: RandomDistortionConfig = field(default_factory=RandomDistortionConfig)
    """Training-time distortions applied to renders before the extractor and classifier."""
    target_psnr: float = 38.0
    """PSNR budget of watermarked vs clean renders; the content loss rises steeply below it."""
    mark_psnr: Optional[float] = 44.0
    """The mark's operating point: the content loss holds watermarked renders this close (PSNR) to the clean ones,
    shrinking a strong mark and growing a faint one, so the mark neither fades toward the renderer's float noise in a
    long run nor stays faint from a weak start; None: the content loss only shrinks the mark."""
    content_weight: float = 1.0
    """Weight of the content loss (MSE, in units of the PSNR budget)."""
    warmup_steps: int = 200
    """No content loss and no distortions for these first steps, then both ramp in over as many steps: the
    extractor first finds the (initially strong) sticker signal, which the content loss then trims to budget."""
    msg_weight: float = 1.0
    """Weight of the message loss (BCE-with-logits, extractor vs message)."""
    negative_weight: float = 0.5
    """Weight of the honesty loss: the extractor's logits on clean renders are pushed to 0 (p = 1/2)."""
    cls_weight: float = 0.1
    """Weight of the classifier loss (watermarked vs clean)."""
    sparse_weight: float = 0.01
    """Weight of the gate's sparsity loss."""
    condition_weight: float = 0.0
    """Fast path: weight of the conditioning loss, the log of the message estimate's variance under white image noise
    of std ``condition_noise`` (from the Gram of one pool view's per-bit render change, ramped in with the content
    loss): it spreads the mark's energy over the bits so the informed image decoder reads noisy images (0: off)."""
    condition_noise: float = 0.1
    """Image noise std the conditioning loss measures the estimate's variance at."""
    condition_blur: float = 0.0
    """Also condition the per-bit change blurred by a Gaussian of this std (px), the low-pass a blur or JPEG leaves
    (the two log-variances are averaged; 0: off)."""
    condition_scale_free: bool = False
    """Divide the variance by the columns' mean energy (trace / bits): the loss then only evens the bits' spectrum
    and the content loss alone sets the mark's strength."""
    seed: int = 0
    """Seed of the pool cameras, messages and distortions (rank r of a distributed run draws its batches with
    seed + r)."""
    pool_cache: Optional[Path] = None
    """Optional file to keep the rendered pool in (reused when base checkpoint, cameras and sizes match)."""


def warmup_ramp(step: int, warmup_steps: int) -> float:
    """The losses' ramp at ``step``: 0 for the first ``warmup_steps`` steps, then linear up to 1 over as many.

    Examples:
        >>> [warmup_ramp(s, 2) for s in range(5)]
        [0.0, 0.0, 0.5, 1.0, 1.0]
    """
    return min(1.0, max(0.0, (step + 1 - warmup_steps) / max(1, warmup_steps)))


def content_loss(mse: Tensor, target_psnr: float, mark_psnr: Optional[float]) -> Tensor:
    """The content loss of a mark whose render differs from the base's by ``mse``.

    With ``b = 10^(-target_psnr/10)`` (the budget) and ``p = 10^(-mark_psnr/10)`` (the operating point)::

        mark_psnr None:  mse / b + 10 relu(mse / b - 1)          (one-sided: pulls every mark toward zero)
        otherwise:       |mse - p| / b + 10 relu(mse / b - 1)    (two-sided: zero at the operating point)

    the second term eleven times steeper past the budget.
    """
    budget = 10.0 ** (-target_psnr / 10.0)
    over = 10.0 * F.relu(mse / budget - 1.0)
    if mark_psnr is None:
        return mse / budget + over
    return (mse - 10.0 ** (-mark_psnr / 10.0)).abs() / budget + over


def is_distributed(world_size: int) -> bool:
    """True when ``world_size`` > 1 processes share an initialized torch.distributed process group."""
    return world_size > 1 and dist.is_available() and dist.is_initialized()


class GeometryStickerPipeline(VanillaPipeline):
    """Frozen base + sticker; a fast training step on cached samples."""

    config: GeometryStickerPipelineConfig
    model: GeometryStickerModel

    def __init__(
        self,
        config: GeometryStickerPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler=None,
    ):
        # The parent is built single-process: no DDP wrap (the training step runs the sticker and heads on cached
        # samples, not the model's forward, so DDP's hooks would sync nothing) and no device_ids barrier.
        super().__init__(config, device, test_mode, 1, 0, grad_scaler)
        hashgrid.speed_up(self.model)
        self.world_size, self.local_rank = world_size, local_rank
        self.rank = comms.get_rank() if self.distributed else 0
        # training draws (or takes) the owner's message; a loaded shared run has none (its sticker is folded)
        self.owner_message: Optional[Tensor] = self.resolve_message(config) if test_mode == "val" else None
        if self.owner_message is not None:
            self.model.set_message(self.owner_message)
        self.message_source = self.source_of_message(config)
        self.owner_label = config.owner_id
        self.resumed_key: Optional[OwnerKey] = None
        # Heads: plain attribute, not a registered submodule (keeps them out of the shareable state dict).
        self.__dict__["heads"] = Heads(config.heads, config.model.num_bits).to(device) if test_mode == "val" else None
        self.distort = RandomDistortion(config.distortion)
        self.generator = torch.Generator().manual_seed(config.seed + self.rank)
        self.pool: List[ViewCache] = []
        self.monitor: List[ViewCache] = []
        self.history: List[Dict[str, float]] = []
        self._t0: Optional[float] = None

    @staticmethod
    def resolve_message(config: GeometryStickerPipelineConfig) -> Tensor:
        """--pipeline.message, else bits derived from the owner ID when asked, else fresh uniformly random bits."""
        if config.message:
            return parse_message(config.message, config.model.num_bits)
        if config.message_from_owner_id:
            return message_from_owner_id(config.owner_id, config.model.num_bits)
        return random_message(config.model.num_bits)

    @staticmethod
    def source_of_message(config: GeometryStickerPipelineConfig) -> str:
        """How :meth:`resolve_message` draws the message for ``config`` (the key records it)."""
        return config.message_source or (
            "given" if config.message else "owner-id" if config.message_from_owner_id else "random"
        )

    def set_owner(self, message: Tensor, source: str, label: str, resumed_key: Optional[OwnerKey] = None) -> None:
        """The owner's message, how it was drawn and the owner's label (the trainer keeps them out of the config);
        ``resumed_key``: the key of the run being resumed (its secret, salt and creation time are kept)."""
        self.owner_message = message.to(torch.long).cpu()
        self.model.set_message(self.owner_message)
        self.message_source, self.owner_label, self.resumed_key = source, label, resumed_key

    def restore_owner(self, key: OwnerKey, heads: bool = True) -> None:
        """Take the owner's side from ``key`` after loading a shared run: the trainable sticker (unfolded), the message
        and how it was drawn, and (``heads``) the heads when this pipeline has them."""
        if key.geometry and bool(self.model.folded):
            self.model.unfold(key.geometry["sticker_state"], key.message, int(key.geometry.get("sticker_seed", -1)))
        if heads and self.heads is not None:
            self.heads.load_state_dict(key.heads_state, strict=True)
        self.set_owner(key.message, key.message_source, key.owner_id, key)

    def shareable_state_dict(self) -> Dict[str, Tensor]:
        """The pipeline state a shared checkpoint holds (see GeometryStickerModel.shareable_state_dict)."""
        return shareable_state(self)

    @property
    def heads(self) -> Optional[Heads]:
        return self.__dict__.get("heads")

    # ------------------------------------------------------------------------------------ several processes
    @property
    def distributed(self) -> bool:
        """True when this pipeline is one rank of a multi-process run (torch.distributed initialized)."""
        return is_distributed(self.world_size)

    @torch.no_grad()
    def broadcast_(self, tensors: Iterable[Tensor]) -> None:
        """Overwrite ``tensors`` in place with rank 0's values (a no-op in a single process)."""
        if not self.distributed:
            return
        for t in tensors:
            buf = t.detach().to(self.device, torch.uint8 if t.dtype == torch.bool else t.dtype).contiguous()
            dist.broadcast(buf, src=0)
            t.copy_(buf)

    def from_rank0(self, tensor: Tensor) -> Tensor:
        """A copy of rank 0's ``tensor`` (``tensor`` itself in a single process)."""
        if not self.distributed:
            return tensor
        out = tensor.clone()
        self.broadcast_([out])
        return out

    def sync_from_rank0(self) -> None:
        """Every rank takes rank 0's sticker, gates, message and heads: all the state but the frozen base."""
        if not self.distributed:
            return
        state = [v for k, v in self.model.state_dict().items() if not k.startswith("base.")]
        if self.heads is not None:
            state += list(self.heads.state_dict().values())
        self.broadcast_(state)

    @torch.no_grad()
    def average_gradients(self, params: Sequence[torch.nn.Parameter]) -> None:
        """Replace each gradient by its mean over the ranks (a rank without one counts zeros); a parameter that no
        rank has a gradient for keeps None. A no-op in a single process."""
        if not self.distributed:
            return
        params = list({id(p): p for p in params}.values())
        if not params:
            return
        grads = [
            p.grad.detach().reshape(-1).to(self.device, torch.float32)
            if p.grad is not None
            else torch.zeros(p.numel(), device=self.device)
            for p in params
        ]
        present = torch.tensor([float(p.grad is not None) for p in params], device=self.device)
        flat = torch.cat([*grads, present])
        dist.all_reduce(flat)
        sums, present = flat[: -len(params)], flat[-len(params) :]
        for p, g, any_rank in zip(params, sums.split([p.numel() for p in params]), present.tolist()):
            if not any_rank:
                continue
            mean = (g / self.world_size).view_as(p).to(p.dtype)
            if p.grad is None:
                p.grad = mean.to(p.device)
            else:
                p.grad.copy_(mean)

    # ------------------------------------------------------------------------------------ state handling
    def get_param_groups(self) -> Dict[str, List[torch.nn.Parameter]]:
        groups = self.model.get_param_groups()
        if self.heads is not None:
            groups["heads"] = list(self.heads.parameters())
        return groups

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: Optional[bool] = None):
        """Strict, unlike the host's (which silently retries with strict=False)."""
        model_state = {k[len("_model.") :]: v for k, v in state_dict.items() if k.startswith("_model.")}
        self.model.load_state_dict(model_state, strict=True)

    def owner_key(self, training_state: Optional[Dict[str, Any]] = None, model_run: str = "") -> OwnerKey:
        assert self.heads is not None and self.owner_message is not None
        key = OwnerKey(
            owner_id=self.owner_label,
            message=self.owner_message.cpu(),
            heads_config=dict(vars(self.config.heads)),
            heads_state=self.heads.state_dict(),
            base=dict(self.config.base_run),
            model_run=model_run,
            training_state=training_state or {},
            geometry=geometry_reference(self.model),
            message_source=self.message_source,
            owner_message_prob=float(self.config.owner_message_prob),
        )
        old = self.resumed_key
        if old is not None and old.secret and old.salt:
            key.secret, key.salt, key.created = old.secret, old.salt, old.created
        return key

    # ------------------------------------------------------------------------------------ fast-path pool
    @torch.no_grad()
    def build_pool(self) -> None:
        """Calibrate the gates (unless resumed) and render the pool views once, sticker off."""
        model = self.model
        cams = self.datamanager.train_dataset.cameras
        gen = torch.Generator().manual_seed(self.config.seed)
        n_train = min(self.config.pool_train_views, cams.shape[0])
        train_idx = torch.randperm(cams.shape[0], generator=gen)[:n_train]
        layout = camera_layout(cams) if self.config.novel_layout == "auto" else self.config.novel_layout
        novel = novel_cameras(cams, self.config.pool_novel_views, gen, layout)
        held = novel_cameras(cams, self.config.monitor_views, gen, layout)
        if not model.calibrated:
            calib = [cache_view(model, cams[int(i) : int(i) + 1].to(self.device), False) for i in train_idx[:4]]
            dens = torch.cat([v.density.reshape(-1, 1) for v in calib])
            w = torch.cat(
                [
                    composite(v.density, v.rgb.float(), v.deltas, model.background_color())[1].reshape(-1, 1)
                    for v in calib
                ]
            )
            for gate in model.gates.values():
                gate.calibrate(
                    dens,
                    w,
                    self.config.model.gate_quantile,
                    self.config.model.beta_ratio,
                    self.config.model.sticker_amplitude,
                )
        mu = float(model.final_wrap.gate.mu)
        cache_id = {
            "base": self.config.base_run.get("checkpoint_sha256", ""),
            "seed": self.config.seed,
            "train": n_train,
            "novel": self.config.pool_novel_views,
            "held": self.config.monitor_views,
            "layout": layout,
            "mu": round(mu, 6),
        }
        path = self.config.pool_cache
        if path is not None and Path(path).is_file():
            try:  # tensors and plain containers only: a cache file is never trusted with arbitrary objects
                saved = torch.load(path, map_location="cpu", weights_only=True)
            except Exception as e:  # unreadable or not a pool cache: rebuilt below
                CONSOLE.print(f"\\[gsticker] pool cache {path} not used ({type(e).__name__}); rendering the pool")
                saved = {}
            if isinstance(saved, dict) and saved.get("id") == cache_id:
                self.pool = [ViewCache(**v) for v in saved["pool"]]
                self.monitor = [ViewCache(**v) for v in saved["monitor"]]
                CONSOLE.print(f"\\[gsticker] pool reused from {path} ({len(self.pool)} views)")
                return
        t0 = time.time()
        jobs = [(cams[int(i) : int(i) + 1], False, self.pool) for i in train_idx]
        jobs += [(novel[i : i + 1], True, self.pool) for i in range(novel.shape[0])]
        jobs += [(held[i : i + 1], True, self.monitor) for i in range(held.shape[0])]
        with Progress(console=CONSOLE, transient=True) as progress:
            task = progress.add_task("Rendering the frozen base into the sticker pool", total=len(jobs))
            for cam, is_novel, dest in jobs:
                dest.append(cache_view(model, cam.to(self.device), is_novel, min_density=0.05 * mu))
                progress.advance(task)
        seen = [coverage(v) for v in self.pool + self.monitor if v.novel]
        CONSOLE.print(
            f"\\[gsticker] novel views ({layout} layout) see the scene in "
            f"{100 * min(seen, default=0):.0f}-{100 * max(seen, default=0):.0f} % of their pixels (accumulation > 0.5)"
        )
        CONSOLE.print(
            f"\\[gsticker] pool: {len(self.pool)} views + {len(self.monitor)} held out, "
            f"{pool_memory_mb(self.pool + self.monitor):.0f} MiB, {time.time() - t0:.0f} s; "
            f"gate mu={mu:.4g}, beta={float(model.final_wrap.gate.beta):.4g}"
        )
        if path is not None and comms.is_main_process():  # one writer when several ranks render the pool
            tmp = Path(str(path) + ".tmp")
            torch.save(
                {"id": cache_id, "pool": [vars(v) for v in self.pool], "monitor": [vars(v) for v in self.monitor]}, tmp
            )
            tmp.replace(path)

    # ------------------------------------------------------------------------------------ training
    def sample_messages(self, n: int) -> Tensor:
        msgs = torch.randint(0, 2, (n, self.config.model.num_bits), generator=self.generator)
        own = torch.rand(n, generator=self.generator) < self.config.owner_message_prob
        msgs[own] = self.owner_message.cpu()
        return msgs.to(self.device)

    def render_batch_fast(self, messages: Tensor):
        bg = self.model.background_color().to(self.device)
        wrap = self.model.final_wrap
        views = [
            self.pool[int(i)] for i in torch.randint(0, len(self.pool), (messages.shape[0],), generator=self.generator)
        ]
        marked, clean, psis = [], [], []
        self._views = views
        for view, msg in zip(views, messages):
            img, psi = render_cached(view, wrap, msg, bg)
            marked.append(img.permute(2, 0, 1))
            clean.append(view.image.permute(2, 0, 1))
            psis.append(psi.reshape(-1))
        return torch.stack(marked), torch.stack(clean).to(self.device), torch.cat(psis)

    def render_batch_naive(self, messages: Tensor):
        """Comparison path: re-render a random patch of a random pool camera through the full base."""
        cams = self.datamanager.train_dataset.cameras
        p = self.config.patch_size
        marked, clean, psis = [], [], []
        for msg in messages:
            i = int(torch.randint(0, cams.shape[0], (1,), generator=self.generator))
            cam = cams[i : i + 1].to(self.device)
            bundle = cam.generate_rays(camera_indices=0, keep_shape=True)
            h, w = bundle.shape[:2]
            y = int(torch.randint(0, max(1, h - p + 1), (1,), generator=self.generator))
            x = int(torch.randint(0, max(1, w - p + 1), (1,), generator=self.generator))
            patch2d = bundle[y : y + p, x : x + p]
            ph, pw = patch2d.shape[:2]  # smaller than p where the image is
            patch = patch2d.flatten()
            self.model.wrap_state.message = msg
            self.model.wrap_state.record = True
            with self.model.final_pass():  # the sticker marks the final field's pass
                out = self.model.base.forward(patch)
            self.model.wrap_state.record = False
            with torch.no_grad(), self.model.sticker_enabled(False):
                ref = self.model.base.forward(patch)
            marked.append(final_rgb(out).reshape(ph, pw, 3).permute(2, 0, 1))  # vanilla-nerf: rgb_fine
            clean.append(final_rgb(ref).reshape(ph, pw, 3).permute(2, 0, 1))
            psis.append(torch.zeros(1, device=self.device))
        return torch.stack(marked), torch.stack(clean), torch.cat(psis)

    def ramp(self, step: int) -> float:
        """Warm-up: 0 for ``warmup_steps`` (no content or conditioning loss, no distortions), then up to 1 over as
        many steps (:func:`warmup_ramp`)."""
        return warmup_ramp(step, self.config.warmup_steps)

    def losses(
        self, marked: Tensor, clean: Tensor, psi: Tensor, messages: Tensor, step: int = 10**9
    ) -> Dict[str, Tensor]:
        heads = self.heads
        assert heads is not None
        cfg = self.config
        mse = F.mse_loss(marked, clean)
        content = content_loss(mse, cfg.target_psnr, cfg.mark_psnr)
        ramp = self.ramp(step)
        losses = {
            "content_loss": cfg.content_weight * ramp * content,
            "sparsity_loss": cfg.sparse_weight * sparsity_loss(psi),
        }
        if not self.trains_heads:  # the informed decoders need no heads: skip their forward passes altogether
            self._last = {"logits": None, "messages": messages, "mse": mse.detach()}
            return losses
        if ramp > 0 and float(torch.rand(1, generator=self.generator)) < ramp:
            marked_d = self.distort(marked, cover=clean, generator=self.generator)
            clean_d = self.distort(clean, generator=self.generator)
        else:
            marked_d, clean_d = marked, clean
        logits = heads.decode(marked_d)
        neg_logits = heads.decode(clean_d)
        cls = heads.classify(torch.cat([marked_d, clean_d]))
        labels = torch.cat([torch.ones(marked.shape[0]), torch.zeros(clean.shape[0])]).to(cls)
        self._last = {"logits": logits.detach(), "messages": messages, "mse": mse.detach()}
        return {
            **losses,
            "message_loss": cfg.msg_weight * F.binary_cross_entropy_with_logits(logits, messages.float()),
            "negative_loss": cfg.negative_weight
            * F.binary_cross_entropy_with_logits(neg_logits, torch.full_like(neg_logits, 0.5)),
            "classifier_loss": cfg.cls_weight * F.binary_cross_entropy_with_logits(cls, labels),
        }

    def conditioning(self, message: Tensor) -> Tuple[Tensor, Tensor]:
        """The message estimate's variance under white noise at one pool view (the batch's first) and the
        conditioning loss's term (``condition_term``) over that view's sharp and, with ``condition_blur``, blurred
        Gram."""
        cfg = self.config
        blurs = (0.0, cfg.condition_blur) if cfg.condition_blur > 0 else (0.0,)
        grams = sign_grams(self._views[0], self.model.final_wrap, message, self.model.background_color(), blurs)
        grams = [g.to(self.device) for g in grams]
        term = condition_term(grams, cfg.condition_noise, cfg.condition_scale_free)
        return noise_variance(grams[0], cfg.condition_noise), term

    @property
    def trains_heads(self) -> bool:
        """False unless ``train_heads`` and a message, honesty or classifier loss weighs above 0: the extractor and
        classifier then stay at their initialization (the owner key still holds them) and no step runs them."""
        c = self.config
        return c.train_heads and bool(c.msg_weight or c.negative_weight or c.cls_weight)

    def get_train_loss_dict(self, step: int):
        if self.config.fast_path and not self.pool:
            self.build_pool()
        if not self.config.fast_path and not self.model.calibrated:
            self.build_pool()
        if self._t0 is None:
            self.sync_from_rank0()  # several ranks: all start from rank 0's sticker, gates (calibrated) and heads
            self._t0 = time.time()
        self.model.train()
        self.heads.train()
        messages = self.sample_messages(self.config.views_per_step)
        if self.config.fast_path:
            marked, clean, psi = self.render_batch_fast(messages)
        else:
            marked, clean, psi = self.render_batch_naive(messages)
        loss_dict = self.losses(marked, clean, psi, messages, step)
        variance = None
        if self.config.condition_weight > 0 and self.config.fast_path:
            variance, term = self.conditioning(messages[0])
            loss_dict["condition_loss"] = (self.config.condition_weight * self.ramp(step) * term).float()
        metrics_dict = {
            "psnr_marked_vs_clean": -10.0 * torch.log10(self._last["mse"].clamp_min(1e-12)),
            "gate_open_share": (psi > 0.5).float().mean() if psi.numel() else torch.tensor(0.0),
            "gate_beta_over_mu": (self.model.final_wrap.gate.beta / self.model.final_wrap.gate.mu).detach(),
        }
        if variance is not None:  # std of the least-squares bit estimate at condition_noise (1 = the bit's size)
            metrics_dict["sign_noise_std"] = variance.detach().sqrt().float()
        if self._last["logits"] is not None:
            metrics_dict["bit_acc"] = metrics.bit_accuracy(metrics.decode_bits(self._last["logits"]), messages).mean()
        if self.config.fast_path and self.monitor and (step + 1) % self.config.steps_per_monitor == 0:
            metrics_dict.update(self.monitor_metrics())
            self.history.append(
                {"step": step + 1, "seconds": time.time() - self._t0, **{k: float(v) for k, v in metrics_dict.items()}}
            )
            CONSOLE.print(
                f"\\[gsticker] step {step + 1}: held-out bit acc {float(metrics_dict['heldout_bit_acc']):.4f} "
                f"(clean renders: {float(metrics_dict['heldout_clean_bit_acc']):.3f}), "
                f"PSNR marked/clean {float(metrics_dict['heldout_psnr']):.2f} dB, "
                f"{time.time() - self._t0:.0f} s"
            )
        return {}, loss_dict, metrics_dict

    @torch.no_grad()
    def monitor_metrics(self) -> Dict[str, Tensor]:
        """Owner-message bit accuracy and PSNR on held-out novel views (fast-path renders, no distortion)."""
        self.heads.eval()
        bg = self.model.background_color().to(self.device)
        owner = self.owner_message.to(self.device)
        accs, clean_accs, psnrs = [], [], []
        for view in self.monitor:
            img, _ = render_cached(view, self.model.final_wrap, owner, bg)
            marked, clean = img.permute(2, 0, 1)[None], view.image.permute(2, 0, 1)[None].to(self.device)
            logits = self.heads.decode(torch.cat([marked, clean]))
            bits = metrics.decode_bits(logits)
            accs.append(metrics.bit_accuracy(bits[:1], owner))
            clean_accs.append(metrics.bit_accuracy(bits[1:], owner))
            psnrs.append(metrics.psnr(marked, clean))
        self.heads.train()
        return {
            "heldout_bit_acc": torch.cat(accs).mean(),
            "heldout_clean_bit_acc": torch.cat(clean_accs).mean(),
            "heldout_psnr": torch.cat(psnrs).mean(),
        }

    def describe(self) -> str:
        h = self.heads
        return (
            f"sticker {count_parameters(self.model.sticker)} params, heads "
            f"{count_parameters(h) if h is not None else 0} params ({self.config.heads.backbone})"
        )
